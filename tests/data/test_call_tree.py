"""call_tree: a stack read back as the calls that made it (any tree of calls, round trip), the executor's own
stacks read as the supervisor's calls, and the text trace."""
import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from php_jax.data import call_tree
from php_jax.data.call_tree import Call
from php_jax.envs import datasets, tasks


def _trees(depth: int):
  """Strategy: a root call (level 0) of `depth` levels, each call below the lowest with 1–3 callees, each
  lowest call 1–4 steps, procedures 0–2 (the root 0); starts and ends filled in by _placed."""
  def at(level):
    if level == depth - 1:
      return st.tuples(st.integers(0, 2), st.integers(1, 4))
    return st.tuples(st.integers(0, 2), st.lists(at(level + 1), min_size=1, max_size=3))
  return st.lists(at(1), min_size=1, max_size=3).map(lambda callees: _placed((0, callees), 0, 0, depth))


def _placed(node, level: int, start: int, depth: int) -> Call:
  procedure, below = node
  if level == depth - 1:
    return Call(level, procedure, start, start + below)
  callees, at = [], start
  for child in below:
    callees.append(_placed(child, level + 1, at, depth))
    at = callees[-1].end
  return Call(level, procedure, start, at, tuple(callees))


def _stack(root: Call, depth: int):
  """The stack [T, d] that a tree of calls puts on: per step, each level's running procedure and its counter
  (the callees it has finished; at the lowest level, the actions it has taken)."""
  procedures, counters = np.zeros((root.end, depth), int), np.zeros((root.end, depth), int)

  def visit(call: Call):
    if not call.callees:
      procedures[call.start:call.end, call.level] = call.procedure
      counters[call.start:call.end, call.level] = np.arange(call.end - call.start)
    for tau, callee in enumerate(call.callees):
      procedures[callee.start:callee.end, call.level] = call.procedure
      counters[callee.start:callee.end, call.level] = tau
      visit(callee)

  visit(root)
  return procedures, counters


@settings(max_examples=60, deadline=None)
@given(st.integers(2, 4).flatmap(lambda depth: st.tuples(st.just(depth), _trees(depth))))
def test_any_tree_of_calls_is_read_back_from_its_stack(case):
  depth, root = case
  procedures, counters = _stack(root, depth)
  assert call_tree.calls(procedures, counters) == root
  per_level = call_tree.level_calls(root)
  assert [c.level for c in per_level[depth - 1]] == [depth - 1] * len(per_level[depth - 1])
  assert sum(c.end - c.start for c in per_level[depth - 1]) == root.end  # the lowest calls tile the steps
  # Counted per procedure, two copies of the stack (one padded) make twice the tree's calls.
  padded = [np.concatenate([x, -np.ones((2, depth), int)]) for x in (procedures, counters)]
  counts = call_tree.calls_per_procedure(np.stack([padded[0], padded[0]]), np.stack([padded[1], padded[1]]),
                                         [root.end, root.end], [1] + [3] * (depth - 1))
  for level, calls in enumerate(per_level):
    np.testing.assert_array_equal(counts[level], 2 * np.bincount([c.procedure for c in calls], minlength=len(
        counts[level])))


def test_padding_beyond_the_length_is_ignored():
  root = Call(0, 0, 0, 3, (Call(1, 1, 0, 2), Call(1, 0, 2, 3)))
  procedures, counters = _stack(root, 2)
  padded = np.concatenate([procedures, -np.ones((2, 2), int)]), np.concatenate([counters, -np.ones((2, 2), int)])
  assert call_tree.calls(*padded, length=3) == root


def test_the_supervisors_stacks_read_as_its_calls():
  """Bubble sort's supervisor on [2, 1]: one pass that swaps, one that does not; every lowest call's steps
  are those its frames cover, and consecutive steps of one call count up from 0."""
  task = tasks.get("bubblesort")
  demos = datasets.problem_demonstrations(task, [(2, 1)], 1)
  n = int(demos.length[0])
  root = call_tree.calls(demos.procedures[0], demos.counters[0], n)
  lowest = call_tree.level_calls(root)[-1]
  for call in lowest:
    np.testing.assert_array_equal(np.asarray(demos.counters[0, call.start:call.end, -1]),
                                  np.arange(call.end - call.start))
  assert root.end == n and lowest[0].start == 0 and lowest[-1].end == n


def test_text_counts_repeated_actions_and_indents_by_level():
  root = Call(0, 0, 0, 5, (Call(1, 0, 0, 4, (Call(2, 1, 0, 3), Call(2, 2, 3, 4))), Call(1, 1, 4, 5, (
      Call(2, 0, 4, 5),))))
  names = [["fulfil"], ["fetch", "deliver"], ["go_left", "go_right", "pick"]]
  lines = call_tree.text(root, lambda level, h: names[level][h], ["right", "right", "right", "pick", "left"])
  assert lines == ["fulfil", "  fetch", "    go_right: right ×3", "    pick: pick", "  deliver",
                   "    go_left: left"]
  assert call_tree.run_lengths(["a", "a", "b", "a"]) == "a ×2, b, a"
