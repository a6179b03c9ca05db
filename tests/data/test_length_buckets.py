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
