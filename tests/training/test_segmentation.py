"""The segmentations: the counters each rule reads off the actions, by hand and against the supervisors'."""
import numpy as np

from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import datasets, tasks
from php_jax.training import joint, segmentation
from php_jax.training.config import TrainConfig


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
  assert segmentation.read_rule(demos, "loops") == segmentation.Rule("loops", frozenset({(p,)}))
  assert segmentation.read_rule(demos, "successors") is None  # every value is followed by several
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


def test_without_loops_a_value_with_one_successor_continues_the_call_by_hand():
  a, b, c, d = 1, 2, 3, 4  # a is always followed by b, d always ends; b and c are followed by several values
  demos = _demos([a, b, c, a, b, d], [c, b, a, b, c])
  assert segmentation.read_rule(demos, "loops") is None
  rule = segmentation.read_rule(demos, "successors")
  assert rule == segmentation.Rule("successors", frozenset({(a,), (d,)}))
  counters = segmentation.segment_counters(demos, rule)
  # calls of the lowest level: [a b] [c] [a b] [d] and [c] [b] [a b] [c]; the level above unknown
  assert counters[0, :, 1].tolist() == [0, 1, 0, 0, 1, 0]
  assert counters[1, :5, 1].tolist() == [0, 0, 0, 1, 0] and counters[1, 5, 1] == UNKNOWN
  assert (counters[..., 0] == UNKNOWN).all()


def test_no_rule_no_segmentation():
  no_loops_no_single = _demos([1, 2, 1, 3, 2], [3, 1])  # every value has two successors or more
  all_loops = _demos([1, 1, 2, 2], [2, 2])  # every value follows itself (and is followed by another)
  for demos in (no_loops_no_single, all_loops):
    assert segmentation.read_rule(demos, "loops") is segmentation.read_rule(demos, "successors") is None
    assert segmentation.hinted_demonstrations(demos, (8, 8, 8), "successors") is None
  addition = datasets.training_demos(tasks.get("addition"), 1, 16, 0)
  assert segmentation.hinted_demonstrations(addition, (8, 8, 8)) is None  # the loops rule: no loops


def test_on_bubble_sort_every_call_the_successors_start_is_the_supervisors():
  task = tasks.get("bubblesort")
  weak, annotated = (datasets.training_demos(task, 1, 128, n) for n in (0, 128))
  rule = segmentation.read_rule(weak, "successors")
  assert rule.name == "successors" and segmentation.read_rule(weak, "loops") is None
  hinted = segmentation.hinted_demonstrations(weak, (16, 9, 3), rule)
  valid = np.arange(weak.actions.shape[1]) < weak.length[:, None]
  starts, true_starts = hinted.counters[..., 2] == 0, annotated.counters[..., 2] == 0
  assert (hinted.counters[valid][:, :2] == UNKNOWN).all() and (hinted.counters[valid][:, 2] != UNKNOWN).all()
  assert (starts[valid] <= true_starts[valid]).all()
  # the calls it misses are the lshift that always follows dece
  missed = true_starts & ~starts & valid
  after_dece = np.zeros_like(missed)
  after_dece[:, 1:] = annotated.procedures[:, :-1, 2] == task.spec.levels[2].index("dece")
  assert missed.any() and (missed == (true_starts & after_dece & valid)).all()
  # a run without annotation takes the segmented calls' length as the lowest level's capacity
  config = TrainConfig(**task.defaults.overrides())
  assert joint.joint_capacity(weak, task.spec, config, (hinted,)) == (16, 9, 3)  # the task's least capacities
  assert joint.joint_capacity(weak, task.spec, TrainConfig(), (hinted,)) == (8, 8, 3)


def test_on_addition_the_successors_cut_calls_where_the_supervisor_does_not():
  task = tasks.get("addition")
  weak, annotated = (datasets.training_demos(task, 1, 160, n) for n in (0, 160))
  hinted = segmentation.hinted_demonstrations(weak, (8, 8, 8), "successors")
  valid = np.arange(weak.actions.shape[1]) < weak.length[:, None]
  wrong = (hinted.counters[..., 2] == 0) & (annotated.counters[..., 2] != 0) & valid
  # MOVE carry LEFT is carry's first action and lshift's third, so the rule cuts both after it
  carry, lshift = (task.spec.levels[2].index(name) for name in ("carry", "lshift"))
  frames = set(zip(annotated.procedures[..., 2][wrong].tolist(), annotated.counters[..., 2][wrong].tolist()))
  assert frames == {(carry, 1), (lshift, 3)}


def test_on_nanocraft_the_segmentation_is_the_supervisors_at_both_levels():
  task = tasks.get("nanocraft")
  for seed in (1, 2):
    weak, annotated = (datasets.training_demos(task, seed, 64, n) for n in (0, 64))
    hinted = segmentation.hinted_demonstrations(weak, (8, 8, 8))
    valid = np.arange(weak.actions.shape[1]) < weak.length[:, None]
    np.testing.assert_array_equal(hinted.counters[valid][:, 1:], annotated.counters[valid][:, 1:])
    assert (hinted.counters[valid][:, 0] == UNKNOWN).all() and (hinted.counters[~valid] == UNKNOWN).all()
    assert (hinted.procedures == UNKNOWN).all()
