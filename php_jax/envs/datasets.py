"""Demonstrations recorded from a task's supervisor (paper §5): training sets by seed, annotated or not."""
from __future__ import annotations

import jax
import numpy as np

from php_jax import demos, executor
from php_jax.envs.task import Task
from php_jax.hierarchy import check_size

MOST_DEMOS = 100_000  # the most demonstrations a command builds from a task's problems in memory
SEED_OFFSETS = {"training": 0, "validation": 10_000, "test": 20_000}  # added to a run's seed per problem set


def oracle_demonstrations(task: Task, states, num_strong: int, max_steps: int) -> demos.Demonstration:
  """The supervisor's demonstrations of a batch of start states; the first num_strong are strongly
  supervised (weak ones keep the supervisor's stack for measuring decoding, flagged strong=False)."""
  batch = jax.tree.leaves(states)[0].shape[0]
  rollouts = executor.rollout_batch(task.oracle, task.spec, task.env, states,
                                    jax.random.split(jax.random.key(0), batch), max_steps)
  return demos.from_rollouts(rollouts, np.arange(batch) < num_strong)


def problem_demonstrations(task: Task, problems: list, num_strong: int) -> demos.Demonstration:
  """oracle_demonstrations of a list of problems (of any sizes), the first num_strong annotated."""
  states, budget = task.states_and_budget(problems)
  return oracle_demonstrations(task, states, num_strong, budget)


def strong_mask(num_demos: int, num_strong: int, seed: int) -> np.ndarray:
  """[num_demos] bool: which demonstrations are strongly supervised, num_strong chosen at random (seeded)."""
  num_demos, num_strong = check_size("num_demos", num_demos, 0), check_size("num_strong", num_strong, 0)
  if not num_strong <= num_demos:
    raise ValueError(f"num_strong must be in 0..{num_demos}; got {num_strong}")
  mask = np.zeros(num_demos, bool)
  mask[np.random.default_rng(seed).permutation(num_demos)[:num_strong]] = True
  return mask


def training_demos(task: Task, seed: int, num_demos: int, num_strong: int) -> demos.Demonstration:
  """The training set of `experiments.train`: the task's training problems for seed, num_strong of them
  (chosen at random, seeded) annotated."""
  problems = task.training_problems(seed, num_demos)
  return problem_demonstrations(task, problems, 0)._replace(strong=strong_mask(len(problems), num_strong, seed))
