"""Run a hierarchy (oracle or learned) on lists of problems and report each episode's outcome.

Problems are batched through the jitted executor. Addition problems are bucketed by tape width (powers of
two) and batches are padded to a fixed size, so a file of mixed lengths compiles a handful of shapes.
"""
from __future__ import annotations

from collections import defaultdict

import jax
import numpy as np

from php_jax import datasets, executor, flat_lstm
from php_jax.envs import addition, nanocraft
from php_jax.hierarchy import HierarchySpec, Policy

NanoCraftProblem = tuple[int, int, int, int, list]  # (x, y, w, h, preplaced [[row, col], ...])


def _width_bucket(num_digits: int) -> int:
  return max(8, 1 << (addition.width_for(num_digits) - 1).bit_length())


def _rollout(policy, spec, env, states, keys, max_steps) -> executor.Rollout:
  """A hierarchy (oracle or PHP) runs in the stack-machine executor; the flat LSTM baseline in its own loop."""
  if isinstance(policy, flat_lstm.FlatLSTMPolicy):
    return flat_lstm.rollout_batch(policy, env, states, max_steps)
  return executor.rollout_batch(policy, spec, env, states, keys, max_steps, record=False)


def _run_batches(policy, spec, env, states_of, items, batch_size, max_steps):
  """Rolls out items in fixed-size batches (the last padded by repetition); yields (item, rollout row)."""
  if not items:
    return
  keys = jax.random.split(jax.random.key(0), batch_size)
  for start in range(0, len(items), batch_size):
    chunk = items[start:start + batch_size]
    padded = chunk + [chunk[0]] * (batch_size - len(chunk))
    rollouts = jax.device_get(_rollout(policy, spec, env, states_of(padded), keys, max_steps))
    for i, item in enumerate(chunk):
      yield item, jax.tree.map(lambda x, i=i: x[i], rollouts)


def solve_addition(policy: Policy, spec: HierarchySpec, problems: list[tuple[str, str]],
                   batch_size: int = 64, budget_factor: int = 2) -> list[dict]:
  """One outcome per problem, in order: {"result", "terminated", "valid", "steps", "correct"}.

  The step budget is budget_factor × the oracle's need for the bucket's longest problem.
  """
  buckets = defaultdict(list)
  for index, (a, _) in enumerate(problems):
    buckets[_width_bucket(len(a))].append(index)
  outcomes = [None] * len(problems)
  for width, indices in sorted(buckets.items()):
    max_steps = budget_factor * addition.oracle_step_budget(width - 2)
    states_of = lambda idx, width=width: datasets.addition_states([problems[i] for i in idx], width)
    size = min(batch_size, len(indices))
    for index, r in _run_batches(policy, spec, addition, states_of, indices, size, max_steps):
      a, b = problems[index]
      result = addition.result(r.final_state)
      outcomes[index] = {"result": result, "terminated": bool(r.terminated), "valid": bool(r.valid),
                         "steps": int(r.length),
                         "correct": bool(r.terminated) and addition.is_correct(result, a, b)}
  return outcomes


def solve_nanocraft(policy: Policy, spec: HierarchySpec, problems: list[NanoCraftProblem],
                    batch_size: int = 256, budget_factor: int = 2) -> list[dict]:
  """One outcome per problem, in order: {"grid", "terminated", "valid", "steps", "correct"}."""
  max_steps = budget_factor * nanocraft.ORACLE_STEP_BUDGET
  indices = list(range(len(problems)))
  states_of = lambda idx: datasets.nanocraft_states([problems[i] for i in idx])
  outcomes = [None] * len(problems)
  for index, r in _run_batches(policy, spec, nanocraft, states_of, indices, min(batch_size, len(problems)),
                               max_steps):
    outcomes[index] = {"grid": np.asarray(r.final_state.grid, int).tolist(),
                       "terminated": bool(r.terminated), "valid": bool(r.valid), "steps": int(r.length),
                       "correct": bool(r.terminated) and bool(nanocraft.solved(r.final_state))}
  return outcomes


SOLVERS = {"addition": solve_addition, "nanocraft": solve_nanocraft}


def accuracy(policy: Policy, spec: HierarchySpec, problems: list) -> float:
  """Fraction of problems solved completely correctly (spec.name picks the task)."""
  outcomes = SOLVERS[spec.name](policy, spec, problems)
  return float(np.mean([o["correct"] for o in outcomes]))
