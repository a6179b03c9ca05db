"""Bubble sort: the environment's rules, the supervisor at every length through evaluate, the training set,
and problem-file lines."""
import json
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from experiments.common import problems as problem_files
from php_jax import demos
from php_jax.envs import bubblesort as bs
from php_jax.envs import bubblesort_task, datasets, evaluation, tasks

BUBBLESORT = tasks.get("bubblesort")


def _act(state, kind, pointer, direction):
  return bs.step(state, jnp.array([kind, pointer, direction], jnp.int32))


def test_observation_swap_and_moves():
  state = bs.make_problem([3, 1, 2], width=8)
  obs = np.asarray(bs.observe(state))
  assert obs.shape == (24,) and obs[3] == 1 and obs[11 + 1] == 1 and obs[22] == 1 and obs[23] == 0
  state = _act(state, bs.SWAP, bs.I, bs.LEFT)
  assert bs.result(state) == [1, 3, 2] and not state.failed
  state = _act(_act(state, bs.MOVE, bs.I, bs.RIGHT), bs.MOVE, bs.J, bs.RIGHT)
  assert np.asarray(state.pointers).tolist() == [1, 2, 3] and not state.failed
  state = _act(state, bs.MOVE, bs.J, bs.RIGHT)  # j = 3 = n: allowed, reads EMPTY, and j = e
  obs = np.asarray(bs.observe(state))
  assert obs[11 + bs.EMPTY] == 1 and obs[23] == 1 and not state.failed


@pytest.mark.parametrize("action, pointers", [
    ((bs.SWAP, bs.J, bs.LEFT), (0, 1, 3)),        # SWAP must name (i, LEFT)
    ((bs.SWAP, bs.I, bs.RIGHT), (0, 1, 3)),
    ((bs.SWAP, bs.I, bs.LEFT), (0, 3, 3)),        # j = n is outside the digits
    ((bs.MOVE, bs.I, bs.LEFT), (0, 1, 3)),        # i below 0
    ((bs.MOVE, bs.E, bs.RIGHT), (0, 1, 3)),       # e above n
    ((2, bs.I, bs.LEFT), (0, 1, 3)),              # no such kind
])
def test_invalid_actions_fail_and_change_nothing_else(action, pointers):
  state = bs.make_problem([3, 1, 2], width=8).replace(pointers=jnp.array(pointers, jnp.int32))
  after = _act(state, *action)
  assert bool(after.failed)
  np.testing.assert_array_equal(after.tape, state.tape)
  np.testing.assert_array_equal(after.pointers, state.pointers)


def _evaluate(tmp_path, lines):
  problems, out = tmp_path / "in.jsonl", tmp_path / "out.jsonl"
  problems.write_text("".join(line + "\n" for line in lines))
  proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--task=bubblesort", "--policy=oracle",
                         f"--problems={problems}", f"--out={out}"], capture_output=True, text=True, timeout=900)
  return proc, out


def _arrays(lengths, seed=0):
  """Per length: a random array, the sorted and the reversed one, and all equal digits."""
  rng = np.random.default_rng(seed)
  arrays = []
  for n in lengths:
    digits = rng.integers(0, 10, n).tolist()
    arrays += [digits, sorted(digits), sorted(digits, reverse=True), [int(rng.integers(10))] * n]
  return arrays


def test_the_oracle_sorts_through_evaluate(tmp_path):
  arrays = _arrays(range(2, 41)) + [[3, 1, 2]]
  proc, out = _evaluate(tmp_path, [json.dumps({"array": a}) for a in arrays])
  assert proc.returncode == 0, proc.stderr
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert [r["result"] for r in rows] == [sorted(a) for a in arrays]
  assert all(r["correct"] and r["terminated"] and r["valid"] for r in rows)
  assert rows[-1] == {"result": [1, 2, 3], "terminated": True, "valid": True, "steps": 16, "correct": True}
  for a, r in zip(arrays, rows):  # within the budget, which the reversed arrays' swaps reach exactly
    assert r["steps"] <= bs.oracle_step_budget(len(a))
  assert rows[2]["steps"] == bs.oracle_step_budget(2) and rows[6]["steps"] == bs.oracle_step_budget(3)


@pytest.mark.slow
def test_the_oracle_sorts_long_arrays():
  """Lengths 64 to 500 (RESULTS.md has the command that runs every length from 2 to 500)."""
  arrays = _arrays((64, 100, 255, 256, 500), seed=1)
  outcomes = evaluation.solve(BUBBLESORT, BUBBLESORT.oracle, [tuple(a) for a in arrays])
  assert all(o["correct"] for o in outcomes)
  assert [o["result"] for o in outcomes] == [sorted(a) for a in arrays]


@pytest.mark.parametrize("line, message", [
    ('{"array": "312"}', 'list field "array"'), ('{"array": [3, 1, "2"]}', "entry 2"),
    ('{"array": [3, 1, 12]}', "entry 2"), ('{"array": [3, true]}', "entry 1"), ('{"array": [3]}', "at least 2"),
    ('{"list": [3, 1]}', "unknown key 'list'"), ('[3, 1]', "JSON object")])
def test_malformed_lines_are_refused_with_their_line_number(tmp_path, line, message):
  path = tmp_path / "in.jsonl"
  path.write_text('{"array": [2, 1]}\n' + line + "\n")
  with pytest.raises(problem_files.ProblemFileError, match=f"{path}:2: malformed bubblesort problem: .*{message}"):
    problem_files.read_problems(str(path), BUBBLESORT)


def test_evaluate_refuses_a_malformed_file_before_writing(tmp_path):
  proc, out = _evaluate(tmp_path, ['{"array": [2, 1]}', '{"array": [3]}'])
  assert proc.returncode == 2 and ":2: malformed bubblesort problem" in proc.stderr and not out.exists()


def test_training_set_compares_every_pair_and_demonstrations_follow_the_call_stack_rules():
  problems = bubblesort_task.training_problems(seed=3)
  assert len(problems) == 128 and sorted({len(p) for p in problems}) == list(range(2, 10))
  assert len(set().union(*map(bubblesort_task.compared_pairs, problems))) == 100
  assert problems == bubblesort_task.training_problems(seed=3) != bubblesort_task.training_problems(seed=4)
  batch = datasets.training_demos(BUBBLESORT, seed=3, num_demos=128, num_strong=128)
  demos.validate(batch, BUBBLESORT.spec)
  lengths = np.asarray(batch.length)
  assert all(n <= bs.oracle_step_budget(len(p)) for n, p in zip(lengths, problems))
  procs = np.asarray(batch.procedures)
  names = BUBBLESORT.spec.levels
  first = [names[2][p] for p in procs[0, :lengths[0], 2]]  # a 2-digit array: one compare, then reset
  assert first[-3:] == ["dece", "lshift", "lshift"] and first[0] in ("swapshift", "shift")
  assert jax.tree.leaves(batch)[0].shape[0] == 128
