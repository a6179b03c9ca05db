"""Bubble sort as a Task: the training set (arrays of 2..9 digits), length-generalization tests,
problem-file lines, outcomes.

A problem is a tuple of n ≥ 2 digits; its bucket is the tape width, a power of two (at least 8) above n.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from php_jax.data.json_lines import check_keys, shown
from php_jax.envs import bubblesort, bubblesort_oracle
from php_jax.envs.task import Task, TrainingDefaults

TRAINING_LENGTHS = tuple(range(2, 10))


def compared_pairs(array) -> set[tuple[int, int]]:
  """The ordered (digit under i, digit under j) pairs that bubble sort compares on this array."""
  a, pairs = list(array), set()
  for end in range(len(a), 1, -1):
    for i in range(end - 1):
      pairs.add((a[i], a[i + 1]))
      if a[i] > a[i + 1]:
        a[i], a[i + 1] = a[i + 1], a[i]
  return pairs


def training_problems(seed: int, per_length: int = 16, lengths=TRAINING_LENGTHS,
                      max_tries: int = 1000) -> list[tuple[int, ...]]:
  """per_length uniformly random arrays for each length, redrawn until every ordered pair of digits is
  compared somewhere in the set. Deterministic in seed."""
  rng = np.random.default_rng(seed)
  for _ in range(max_tries):
    problems = [tuple(int(d) for d in rng.integers(0, 10, n)) for n in lengths for _ in range(per_length)]
    if len(set().union(*map(compared_pairs, problems))) == 100:
      return problems
  raise RuntimeError(f"no training set compares every pair of digits in {max_tries} draws; add arrays")


def random_problems(seed: int, num: int, length: int | None = None) -> list[tuple[int, ...]]:
  """num uniformly random arrays of `length` digits (None: lengths uniform in 2..9). Deterministic in seed."""
  rng = np.random.default_rng(seed)
  sizes = rng.integers(TRAINING_LENGTHS[0], TRAINING_LENGTHS[-1] + 1, num) if length is None else [length] * num
  return [tuple(int(d) for d in rng.integers(0, 10, n)) for n in sizes]


def bucket(problem: tuple[int, ...]) -> int:
  """The tape width for an array: a power of two, at least 8, above its length."""
  return max(8, 1 << len(problem).bit_length())


def make_states(problems: list[tuple[int, ...]], width: int) -> bubblesort.State:
  """Batched start states [B, ...] on a common tape width."""
  states = [bubblesort.make_problem(p, width) for p in problems]
  return jax.tree.map(lambda *x: jnp.asarray(np.stack(x)), *states)  # one host copy, not a jnp.stack of B operands


_MAX_LENGTH = (1 << 14) - 1  # a longer array's tape (2^15) has a step budget beyond 32-bit step counts


def parse_problem(obj: dict) -> tuple[int, ...]:
  """{"array": [3, 1, 2]} → (3, 1, 2): 2 to _MAX_LENGTH digits."""
  check_keys(obj, ("array",))
  array = obj.get("array")
  if not isinstance(array, list):
    raise ValueError('needs a list field "array"')
  if not 2 <= len(array) <= _MAX_LENGTH:
    raise ValueError(f'"array" must hold at least 2 digits and at most {_MAX_LENGTH} (beyond, its step budget '
                     f'overflows 32-bit step counts); got {len(array)}')
  for position, d in enumerate(array):
    if not (isinstance(d, int) and not isinstance(d, bool) and 0 <= d <= 9):
      raise ValueError(f'"array" entries must be digits 0-9; entry {position} is {shown(d)}')
  return tuple(array)



def outcome(problem: tuple[int, ...], final_state: bubblesort.State) -> tuple[dict, bool]:
  """({"result": the tape's digits}, whether they are the sorted input)."""
  result = bubblesort.result(final_state)
  return {"result": result}, result == sorted(problem)


def action_name(action: list[int]) -> str:
  """[kind, pointer, direction] → e.g. "SWAP i LEFT", "MOVE e RIGHT" (the raw list if it names no action)."""
  kind, pointer, direction = action
  if kind in (bubblesort.MOVE, bubblesort.SWAP) and 0 <= pointer <= bubblesort.E and direction in (
      bubblesort.LEFT, bubblesort.RIGHT):
    return (f"{'MOVE' if kind == bubblesort.MOVE else 'SWAP'} {'ije'[pointer]} "
            f"{'LEFT' if direction == bubblesort.LEFT else 'RIGHT'}")
  return str(list(action))


TASK = Task(
    name="bubblesort", env=bubblesort, spec=bubblesort_oracle.SPEC, oracle=bubblesort_oracle.BubbleSortOracle(),
    training_problems=lambda seed, num: training_problems(seed),
    validation_problems=random_problems, test_problems=random_problems,
    bucket=bucket, make_states=make_states,
    step_budget=lambda width: bubblesort.oracle_step_budget(width - 1),
    parse_problem=parse_problem, outcome=outcome,
    # Every return but the lowest procedures' reads the observation. The root's decisions need no counter and
    # level 1's only whether an operation is reset's first (so they behave the same on arrays of any length).
    # The calls grow with the array, beyond the longest annotated one when few arrays are annotated: level 1's
    # (reset makes n of them, 9 in the training set) and the root's (bubble and reset in turn, 2(n − 1): 16),
    # which a joint run without annotation has no annotated call to size from. Without annotation the recipe
    # finds the successors segmentation from the actions (RESULTS.md). Level-wise where some array is
    # annotated: joint training solves it too, at about 4.6× the time (RESULTS.md).
    defaults=TrainingDefaults(num_demos=128, num_demos_fixed=True, hidden=(64,),
                              tau_in_termination=(False, False, True), tau_limit=(0, 1, None),
                              min_capacity=(16, 9, 3), test_lengths=(20, 50, 100, 200), num_test=100,
                              iterations=1000, learning_rate=1e-2,
                              training="levelwise"),
    action_name=action_name)
