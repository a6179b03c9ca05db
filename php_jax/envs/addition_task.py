"""Long-hand addition as a Task: the paper's training set, problem sampling, problem-file lines, outcomes.

A problem is (a, b), two decimal strings of equal length (most significant digit first); its bucket is the
tape width, a power of two (at least 8) that fits the sum.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from php_jax.data.json_lines import check_keys, shown
from php_jax.envs import addition, addition_oracle
from php_jax.envs.task import Task, TrainingDefaults

TRAINING_LENGTHS = tuple(range(1, 11))


def column_triples(a: str, b: str) -> set[tuple[int, int, int]]:
  """The (digit1, digit2, carry-in) of every column of a + b."""
  triples, carry = set(), 0
  for d1, d2 in zip(map(int, reversed(a)), map(int, reversed(b))):
    triples.add((d1, d2, carry))
    carry = (d1 + d2 + carry) // 10
  return triples


def training_problems(seed: int, per_length: int = 16, lengths=TRAINING_LENGTHS,
                      max_tries: int = 1000) -> list[tuple[str, str]]:
  """per_length random problems for each number of digits, redrawn until every one of the 200
  (digit1, digit2, carry-in) columns occurs (paper §5.2, footnote 2). Deterministic in seed."""
  rng = np.random.default_rng(seed)
  for _ in range(max_tries):
    problems = [tuple("".join(map(str, row)) for row in rng.integers(0, 10, (2, n)))
                for n in lengths for _ in range(per_length)]
    covered = set().union(*(column_triples(a, b) for a, b in problems))
    if len(covered) == 200:
      return problems
  raise RuntimeError(f"no problem set covering all 200 columns in {max_tries} draws; add problems")


def covering_problems(seed: int, digits: int) -> list[tuple[str, str]]:
  """A small set of `digits`-digit problems in which every one of the 200 (digit1, digit2, carry-in) columns
  occurs: built column by column from the lowest, each time taking a not yet covered column whose carry-in
  is the running carry (any column with that carry-in once none is left). Deterministic in seed."""
  if digits < 2:
    raise ValueError(f"digits must be at least 2 (a 1-digit sum has no carry-in); got {digits}")
  rng = np.random.default_rng(seed)
  missing = {(d1, d2, c) for d1 in range(10) for d2 in range(10) for c in range(2)}
  problems = []
  while missing:
    columns, carry = [], 0
    for _ in range(digits):
      options = sorted(t for t in missing if t[2] == carry) or [(d1, d2, carry) for d1 in range(10)
                                                                for d2 in range(10)]
      d1, d2, _ = options[rng.integers(len(options))]
      missing.discard((d1, d2, carry))
      columns.append((d1, d2))
      carry = (d1 + d2 + carry) // 10
    problems.append(tuple("".join(str(col[i]) for col in reversed(columns)) for i in range(2)))
  return problems


def random_problems(seed: int, lengths, per_length: int) -> list[tuple[str, str]]:
  """per_length uniformly random problems for each number of digits in lengths (no coverage constraint)."""
  rng = np.random.default_rng(seed)
  return [tuple("".join(map(str, rng.integers(0, 10, n))) for _ in range(2))
          for n in lengths for _ in range(per_length)]


def make_states(problems: list[tuple[str, str]], width: int | None = None) -> addition.State:
  """Batched start states [B, ...] on a common tape width (default: fits the longest problem)."""
  width = width or addition.width_for(max(len(a) for a, _ in problems))
  states = [addition.make_problem(a, b, width) for a, b in problems]
  return jax.tree.map(lambda *x: jnp.asarray(np.stack(x)), *states)  # one host copy, not a jnp.stack of B operands


def bucket(problem: tuple[str, str]) -> int:
  """The tape width for a problem: a power of two, at least 8, that fits its sum."""
  return max(8, 1 << (addition.width_for(len(problem[0])) - 1).bit_length())


_MAX_DIGITS = (1 << 20) - 2  # tapes of at most 2^20 columns: a batch of 64 problems holds 1 GiB of tapes


def parse_problem(obj: dict) -> tuple[str, str]:
  """{"a": "0123", "b": "4567"} → ("0123", "4567"): equal lengths, at most _MAX_DIGITS digits."""
  check_keys(obj, ("a", "b"))
  a, b = obj.get("a"), obj.get("b")
  if not isinstance(a, str) or not isinstance(b, str):
    raise ValueError('needs string fields "a" and "b"')
  if max(len(a), len(b)) > _MAX_DIGITS:
    raise ValueError(f'"a" and "b" may have at most {_MAX_DIGITS} digits (tapes of 2^20 columns); got '
                     f'{len(a)} and {len(b)}')
  if not (a.isascii() and a.isdigit() and b.isascii() and b.isdigit()):
    raise ValueError(f'"a" and "b" must be non-empty strings of decimal digits; got {shown(a)}, {shown(b)}')
  if len(a) != len(b):
    raise ValueError(f'"a" and "b" must have the same number of digits; got {len(a)} and {len(b)}')
  return a, b



def outcome(problem: tuple[str, str], final_state: addition.State) -> tuple[dict, bool]:
  """({"result": the out tape's number}, whether it is a + b)."""
  result = addition.result(final_state)
  return {"result": result}, addition.is_correct(result, *problem)


def action_name(action: list[int]) -> str:
  """[kind, tape, arg] → "MOVE in1 RIGHT" / "WRITE out 7" (the raw list if it names no action)."""
  kind, tape, arg = action
  if kind == addition.MOVE and 0 <= tape < addition.NUM_TAPES and arg in (addition.LEFT, addition.RIGHT):
    return f"MOVE {addition.TAPE_NAMES[tape]} {'LEFT' if arg == addition.LEFT else 'RIGHT'}"
  if kind == addition.WRITE and 0 <= tape < addition.NUM_TAPES and 0 <= arg <= 9:
    return f"WRITE {addition.TAPE_NAMES[tape]} {arg}"
  return str(list(action))


TASK = Task(
    name="addition", env=addition, spec=addition_oracle.SPEC, oracle=addition_oracle.AdditionOracle(),
    training_problems=lambda seed, num: training_problems(seed),
    validation_problems=lambda seed, num: random_problems(seed, TRAINING_LENGTHS, max(1, num // 10)),
    test_problems=lambda seed, num, length: random_problems(
        seed + (length or 0), [length] if length else TRAINING_LENGTHS, num if length else max(1, num // 10)),
    bucket=bucket, make_states=make_states,
    step_budget=lambda width: addition.oracle_step_budget(width - 2),
    parse_problem=parse_problem, outcome=outcome,
    # One hidden layer of 64: solved every test length with 1, 3, 10 strong, twice as fast as (64, 64).
    # add's ψ needs no counter; add1's and the lowest level's do. The training mode is the recipe's (level-wise
    # kept on every seed measured: RESULTS.md, the recipe).
    defaults=TrainingDefaults(num_demos=160, num_demos_fixed=True, hidden=(64,),
                              tau_in_termination=(False, True, True), test_lengths=(20, 100), num_test=100),
    action_name=action_name)
