"""Length buckets: the split that pads least, checked against every split by brute force, and the padded
share a run logs."""
import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from php_jax.data import views
from php_jax.envs import datasets, tasks


def _fewest_padded(lengths, num_buckets) -> int:
  """The fewest padded cells (Σ group size × its longest) over every split of the sorted lengths into at most
  num_buckets contiguous groups."""
  ordered = np.sort(lengths)
  return min(sum(len(part) * part.max() for part in np.split(ordered, cuts))
             for k in range(1, min(num_buckets, len(ordered)) + 1)
             for cuts in itertools.combinations(range(1, len(ordered)), k - 1))


@settings(max_examples=150, deadline=None)
@given(st.lists(st.integers(1, 9), min_size=1, max_size=10), st.integers(1, 5))
def test_the_groups_pad_least_hold_every_index_once_and_number_min_of_buckets_and_rows(lengths, num_buckets):
  lengths = np.asarray(lengths)
  groups = views.length_groups(lengths, num_buckets)
  assert sorted(np.concatenate([g for g, _ in groups]).tolist()) == list(range(len(lengths)))
  assert len(groups) == min(num_buckets, len(lengths)) and all(len(g) for g, _ in groups)
  assert all(width == lengths[g].max() for g, width in groups)
  assert sum(len(g) * width for g, width in groups) == _fewest_padded(lengths, num_buckets)


def test_a_long_outlier_gets_a_bucket_of_its_own_where_equal_counts_would_pad_a_quarter_to_it():
  lengths = np.array([2] * 9 + [3] * 6 + [40])
  groups = views.length_groups(lengths, 2)
  assert [int(w) for _, w in groups] == [3, 40] and len(groups[1][0]) == 1
  buckets = views.length_buckets(datasets.training_demos(tasks.get("nanocraft"), 1, 8, 0), 2)
  padding = views.padding_fraction(buckets)
  steps = sum(int(np.sum(b.length)) for b in buckets)
  computed = sum(b.actions.shape[0] * b.actions.shape[1] for b in buckets)
  assert 0 <= padding < 1 and np.isclose(padding, 1 - steps / computed)


def _padding(lengths, count) -> float:
  groups = views.length_groups(lengths, count)
  return 1 - lengths.sum() / sum(len(g) * width for g, width in groups)


@settings(max_examples=100, deadline=None)
@given(st.lists(st.integers(1, 200), min_size=1, max_size=60))
def test_bucket_count_is_the_fewest_from_4_to_8_that_pad_at_most_a_quarter(lengths):
  lengths = np.asarray(lengths)
  count = views.bucket_count(lengths)
  assert views.LEAST_BUCKETS <= count <= views.MOST_BUCKETS
  assert all(_padding(lengths, c) > views.MOST_PADDING for c in range(views.LEAST_BUCKETS, count))
  assert count == views.MOST_BUCKETS or _padding(lengths, count) <= views.MOST_PADDING
  assert len(views.length_buckets(views.LevelView(*[np.zeros((len(lengths), 1))] * 4, lengths, *[np.zeros(
      len(lengths))] * 3), None)) == min(count, len(lengths))


def test_lengths_spread_far_get_more_buckets_and_a_run_records_how_many():
  from php_jax.demos import Demonstration, UNKNOWN
  from php_jax.hierarchy import HierarchySpec
  from php_jax.training.config import TrainConfig, resolved
  spread = np.unique(np.round(np.logspace(0, 3, 60)).astype(int))  # lengths 1 to 1,000, evenly on a log scale
  assert [round(_padding(spread, c), 2) for c in (4, 5, 6)] == [0.32, 0.26, 0.22] and views.bucket_count(spread) == 6
  assert views.bucket_count(np.array([5] * 10 + [6] * 10)) == 4
  spec = HierarchySpec("t", (("r",), ("a",)), (2,), 1)
  width = int(spread.max())
  demos = Demonstration(np.zeros((len(spread), width + 1, 1), np.float32), np.zeros((len(spread), width, 1), np.int32),
                        np.full((len(spread), width, 2), UNKNOWN, np.int32), np.full((len(spread), width, 2), UNKNOWN,
                                                                                     np.int32),
                        spread.astype(np.int32), np.zeros(len(spread), bool))
  assert resolved(TrainConfig(), demos, spec).length_buckets == views.bucket_count(spread)
  assert resolved(TrainConfig(length_buckets=2), demos, spec).length_buckets == 2


def test_seeds_trained_together_take_the_most_buckets_any_of_them_needs():
  from php_jax.training.config import TrainConfig, with_common_buckets
  configs = with_common_buckets([TrainConfig(seed=1, length_buckets=4), TrainConfig(seed=2, length_buckets=6)])
  assert [c.length_buckets for c in configs] == [6, 6] and [c.seed for c in configs] == [1, 2]
