"""Problem sets and oracle demonstrations for the benchmarks (paper §5, DESIGN.md §5)."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

from php_jax import demos, executor
from php_jax.envs import addition, nanocraft
from php_jax.tasks import TASKS, Task

ADDITION_LENGTHS = tuple(range(1, 11))


def column_triples(a: str, b: str) -> set[tuple[int, int, int]]:
  """The (digit1, digit2, carry-in) of every column of a + b."""
  triples, carry = set(), 0
  for d1, d2 in zip(map(int, reversed(a)), map(int, reversed(b))):
    triples.add((d1, d2, carry))
    carry = (d1 + d2 + carry) // 10
  return triples


def addition_problems(seed: int, per_length: int = 16, lengths=ADDITION_LENGTHS,
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


def covering_addition_problems(seed: int, digits: int) -> list[tuple[str, str]]:
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


def random_addition_problems(seed: int, lengths, per_length: int) -> list[tuple[str, str]]:
  """per_length uniformly random problems for each number of digits in lengths (no coverage constraint)."""
  rng = np.random.default_rng(seed)
  return [tuple("".join(map(str, rng.integers(0, 10, n))) for _ in range(2))
          for n in lengths for _ in range(per_length)]


def addition_states(problems: list[tuple[str, str]], width: int | None = None) -> addition.State:
  """Batched start states [B, ...] on a common tape width (default: fits the longest problem)."""
  width = width or addition.width_for(max(len(a) for a, _ in problems))
  states = [addition.make_problem(a, b, width) for a, b in problems]
  return jax.tree.map(lambda *x: jnp.stack(x), *states)


def nanocraft_problems(seed: int, num: int, place_prob: float = 0.5) -> list[tuple]:
  """num random NanoCraft problems (x, y, w, h, preplaced): a building drawn uniformly from the 100 specs,
  each perimeter cell pre-placed with place_prob. Deterministic in seed."""
  rng = np.random.default_rng(seed)
  problems = []
  for index in rng.integers(0, len(nanocraft.SPECS), num):
    x, y, w, h = (int(v) for v in nanocraft.SPECS[index])
    cells = np.argwhere(np.asarray(nanocraft.perimeter(nanocraft.SPECS[index])))
    problems.append((x, y, w, h, [c.tolist() for c in cells if rng.random() < place_prob]))
  return problems


def nanocraft_states(problems: list[tuple]) -> nanocraft.State:
  """Batched start states [B, ...] for (x, y, w, h, preplaced) problems."""
  states = [nanocraft.make_problem(x, y, w, h, pre) for x, y, w, h, pre in problems]
  return jax.tree.map(lambda *x: jnp.stack(x), *states)


def oracle_demonstrations(task: Task, states, num_strong: int, max_steps: int) -> demos.Demonstration:
  """The supervisor's demonstrations of a batch of problems; the first num_strong are strongly supervised
  (weak ones keep the supervisor's stack for measuring decoding, flagged strong=False)."""
  batch = jax.tree.leaves(states)[0].shape[0]
  rollouts = executor.rollout_batch(task.oracle, task.spec, task.env, states,
                                    jax.random.split(jax.random.key(0), batch), max_steps)
  return demos.from_rollouts(rollouts, np.arange(batch) < num_strong)


def strong_mask(num_demos: int, num_strong: int, seed: int) -> np.ndarray:
  """[num_demos] bool: which demonstrations are strongly supervised, num_strong chosen at random (seeded)."""
  if not 0 <= num_strong <= num_demos:
    raise ValueError(f"num_strong must be in 0..{num_demos}; got {num_strong}")
  mask = np.zeros(num_demos, bool)
  mask[np.random.default_rng(seed).permutation(num_demos)[:num_strong]] = True
  return mask


def nanocraft_training_demos(seed: int, num_demos: int, num_strong: int) -> demos.Demonstration:
  """The training set of `experiments.nanocraft`: num_demos random episodes, num_strong annotated."""
  problems = nanocraft_problems(seed, num_demos)
  return oracle_demonstrations(TASKS["nanocraft"], nanocraft_states(problems), 0, nanocraft.ORACLE_STEP_BUDGET
                               )._replace(strong=strong_mask(num_demos, num_strong, seed))


def addition_training_demos(seed: int, num_strong: int) -> demos.Demonstration:
  """The training set of `experiments.addition`: 160 traces (16 per length 1..10), num_strong annotated."""
  problems = addition_problems(seed)
  return oracle_demonstrations(TASKS["addition"], addition_states(problems), 0, addition.oracle_step_budget(10)
                               )._replace(strong=strong_mask(len(problems), num_strong, seed))
