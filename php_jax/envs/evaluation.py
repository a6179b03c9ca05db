"""Run a hierarchy (oracle or learned) on lists of a task's problems and report each episode's outcome.

Problems are batched through the jitted executor by the task's bucket (one state shape each), and batches
are padded to a fixed size, so a file of mixed sizes compiles a handful of shapes.
"""
from __future__ import annotations

from collections import defaultdict

import jax
import numpy as np

from php_jax import executor, flat
from php_jax.envs.task import Task
from php_jax.hierarchy import HierarchySpec


def rollout(policy, spec: HierarchySpec, env, states, keys, max_steps: int) -> executor.Rollout:
  """The outcomes (nothing recorded) of a batch of episodes from states [B, ...]: a hierarchy (oracle or PHP)
  runs in the stack-machine executor, a flat baseline in its own loop."""
  if isinstance(policy, flat.FlatPolicy):
    return flat.rollout_batch(policy, env, states, keys, max_steps)
  return executor.rollout_batch(policy, spec, env, states, keys, max_steps, record=False)


def solve(task: Task, policy, problems: list, batch_size: int = 64, budget_factor: int = 2) -> list[dict]:
  """One outcome per problem, in order: the task's fields (e.g. "result"), then "terminated", "valid",
  "steps" and "correct" (terminated with the right answer), and for an episode that did not terminate
  validly "failure": why (the invalid action and its step, or the exhausted step budget).

  The step budget is budget_factor × the oracle's need for the bucket's largest problem.
  """
  if batch_size < 1:
    raise ValueError(f"batch_size must be at least 1; got {batch_size}")
  buckets = defaultdict(list)
  for index, problem in enumerate(problems):
    buckets[task.bucket(problem)].append(index)
  outcomes = [None] * len(problems)
  for bucket, indices in sorted(buckets.items()):
    size = min(batch_size, len(indices))
    keys = jax.random.split(jax.random.key(0), size)
    max_steps = budget_factor * task.step_budget(bucket)
    for start in range(0, len(indices), size):
      chunk = indices[start:start + size]
      padded = chunk + [chunk[0]] * (size - len(chunk))
      states = task.make_states([problems[i] for i in padded], bucket)
      rollouts = jax.device_get(rollout(policy, task.spec, task.env, states, keys, max_steps))
      for row, index in enumerate(chunk):
        r = jax.tree.map(lambda x, row=row: x[row], rollouts)
        fields, right = task.outcome(problems[index], r.final_state)
        outcomes[index] = {**fields, "terminated": bool(r.terminated), "valid": bool(r.valid),
                           "steps": int(r.length), "correct": bool(r.terminated) and bool(right)}
        if not r.valid:
          action = task.action_name([int(a) for a in r.failed_action])
          outcomes[index]["failure"] = f"invalid action {action} at step {int(r.length)}"
        elif not r.terminated:
          outcomes[index]["failure"] = f"step budget exhausted after {int(r.length)} steps"
  return outcomes


def accuracy(task: Task, policy, problems: list) -> float:
  """Fraction of problems solved completely correctly. Raises ValueError for no problems (no fraction)."""
  if not problems:
    raise ValueError("accuracy needs at least one problem")
  return float(np.mean([o["correct"] for o in solve(task, policy, problems)]))
