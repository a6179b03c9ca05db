"""The loop segmentation: the counters it reads off the actions, by hand and against NanoCraft's supervisor."""
import numpy as np

from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import datasets, tasks
from php_jax.training import segmentation


def _demos(*action_rows, strong=None):
  """Actions-only demonstrations with one action factor, padded with action 0 to the longest."""
  width = max(map(len, action_rows))
  actions = np.zeros((len(action_rows), width, 1), np.int32)
  for b, row in enumerate(action_rows):
    actions[b, :len(row), 0] = row
  stacks = np.full((len(action_rows), width, 3), UNKNOWN, np.int32)
  return Demonstration(np.zeros((len(action_rows), width + 1, 2), np.float32), actions, stacks, stacks.copy(),
                       np.array([len(r) for r in action_rows]), np.zeros(len(action_rows), bool)
                       if strong is None else np.asarray(strong))


def test_counters_follow_both_assumptions_by_hand():
  a, b, p = 1, 2, 9  # a and b follow themselves; p never does
  demos = _demos([a, a, p, a, p, b, b, p, a], [b, p, b, p, b])
  assert segmentation.attached_actions(demos) == {(p,)}
  counters = segmentation.loop_counters(demos, {(p,)})
  # calls of the lowest level: [a] [a p] [a p] [b] [b p] [a]; the level above: [a, a p, a p] [b, b p] [a]
  assert counters[0, :9].tolist() == [[0, 0], [1, 0], [1, 1], [2, 0], [2, 1], [0, 0], [1, 0], [1, 1], [0, 0]]
  assert counters[1, :5].tolist() == [[0, 0], [0, 1], [1, 0], [1, 1], [2, 0]]
  assert (counters[1, 5:] == UNKNOWN).all()


def test_the_hints_are_partial_annotations_within_capacity_and_annotated_demonstrations_stay():
  a, p = 1, 9
  demos = _demos([a, a, a, p], [a, p, a, p], strong=[False, True])
  demos = demos._replace(procedures=np.where(demos.strong[:, None, None], 0, demos.procedures))
  hinted = segmentation.hinted_demonstrations(demos, (9, 2, 5))
  assert hinted.strong.all()
  assert (hinted.procedures[0] == UNKNOWN).all() and (hinted.procedures[1] == 0).all()
  # the level-1 counter 2 is at its capacity 2: unknown there
  assert hinted.counters[0].tolist() == [[UNKNOWN, 0, 0], [UNKNOWN, 1, 0], [UNKNOWN, UNKNOWN, 0], [UNKNOWN, UNKNOWN, 1]]
  assert (hinted.counters[1] == demos.counters[1]).all()


def test_no_loops_no_segmentation():
  assert segmentation.attached_actions(_demos([1, 2, 1, 3], [2, 3])) is None  # nothing follows itself
  assert segmentation.attached_actions(_demos([1, 1, 2, 2], [2, 2])) is None  # everything does
  for name in ("addition", "bubblesort"):
    demos = datasets.training_demos(tasks.get(name), 1, 16, 0)
    assert segmentation.hinted_demonstrations(demos, (8, 8, 8)) is None


def test_on_nanocraft_the_segmentation_is_the_supervisors_at_both_levels():
  task = tasks.get("nanocraft")
  for seed in (1, 2):
    weak, annotated = (datasets.training_demos(task, seed, 64, n) for n in (0, 64))
    hinted = segmentation.hinted_demonstrations(weak, (8, 8, 8))
    valid = np.arange(weak.actions.shape[1]) < weak.length[:, None]
    np.testing.assert_array_equal(hinted.counters[valid][:, 1:], annotated.counters[valid][:, 1:])
    assert (hinted.counters[valid][:, 0] == UNKNOWN).all() and (hinted.counters[~valid] == UNKNOWN).all()
    assert (hinted.procedures == UNKNOWN).all()
