"""Joint Expectation–Gradient training: every level at once, with the hierarchy's own root (no stand-in).

The loss is `objective.stack_loss`, the weighted negative log-likelihood of the demonstrations' elementary
actions under the whole hierarchy; its gradient is the EG gradient of every level's networks at once.
Demonstrations are batched by length into buckets.
"""
from __future__ import annotations

import time
from typing import Callable

import jax
import numpy as np
from jax.sharding import Mesh

from php_jax import fitting, sharding
from php_jax.data import views
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import call_graph, checkpoint, train
from php_jax.training.objective import annealed_temperature, counter_capacity, stack_loss


def joint_capacity(demos: Demonstration, spec: HierarchySpec, config: train.TrainConfig) -> tuple[int, ...]:
  """Counter capacity per level, root first (`objective.counter_capacity` of the strong demonstrations'
  counters at that level; config.capacity when nothing is annotated, at least config.min_capacity). The
  root's longest annotated call is scaled by how much longer the longest demonstration is than the longest
  annotated one: weak demonstrations may need more root operations."""
  taus, strong, lengths = np.asarray(demos.counters), np.asarray(demos.strong), np.asarray(demos.length)
  least = config.min_capacity or (0,) * spec.num_levels
  return tuple(counter_capacity(taus[strong][..., level], config.capacity, least[level],
                                *((lengths.max(), lengths[strong].max()) if level == 0 and strong.any() else ()))
               for level in range(spec.num_levels))


def _buckets(demos: Demonstration, num_buckets: int,
             mesh: Mesh | None = None) -> list[tuple[Demonstration, jax.Array]]:
  """`views.length_buckets` of demos as device arrays (`views.device_demonstrations`): (batch, real [B])."""
  return [views.device_demonstrations(bucket, mesh) for bucket in views.length_buckets(demos, num_buckets)]


def train_joint(spec: HierarchySpec, demos: Demonstration, config: train.TrainConfig,
                validate: Callable[[PHPHierarchy], float] | None = None, log: Callable[[dict], None] = print,
                checkpoint_path: str | None = None) -> tuple[PHPHierarchy, dict]:
  """Trains every level together (config.training unset or "joint", else ValueError) for config.iterations
  Adam iterations, keeping the snapshot with the best validate(hierarchy) (config.snapshot's rule).
  Checkpoints and resumes as train.train_hierarchy does
  (the same log protocol); a checkpoint made with other settings raises CheckpointError. Returns the
  hierarchy and a report {capacity, losses, best_iteration, validation, seconds}."""
  config = train.prepare(spec, demos, train.in_mode(config, "joint"))
  hierarchy = train.make_hierarchy(spec, config, call_graph.resolve(config.call_graph, demos, spec))
  settings = train.run_settings(spec, demos, config)
  capacity = joint_capacity(demos, spec, config)
  saved = checkpoint.read_training(checkpoint_path)
  counted_log, resume = train.CountedLog(log), None
  if saved is not None:
    counted_log.resumed(train.resume_from(checkpoint_path, saved, settings, hierarchy))
    resume = checkpoint.restore_progress(checkpoint_path, saved, hierarchy) if saved[0]["progress"] else None
  if resume is None:
    counted_log({"training": "joint", "capacity": list(capacity)})

  def save(progress: fitting.Progress) -> None:
    if checkpoint_path:
      checkpoint.write_training(checkpoint_path, hierarchy, {"level": "joint", "report": {}, "settings": settings,
                                                             "logged": counted_log.logged}, progress, {})

  start = time.time()
  mesh = sharding.data_mesh()  # with more than one device, each bucket is split over all of them
  buckets = _buckets(demos, config.length_buckets, mesh)
  schedule = config.schedule()
  hooks = fitting.Hooks((lambda it, loss: validate(hierarchy)) if validate else None, counted_log,
                        save if checkpoint_path else None)
  annealed = config.anneal_temperature != 1
  if annealed:  # the loss logged while T > 1 is the tempered one
    def loss(h, iteration, buckets):
      temperature = annealed_temperature(config.anneal_temperature, iteration, config.iterations)
      return stack_loss(h, buckets, capacity, config.strong_weight, temperature, config.call_penalty)
  else:
    def loss(h, buckets):
      return stack_loss(h, buckets, capacity, config.strong_weight, call_penalty=config.call_penalty)
  progress = fitting.fit(hierarchy, loss, schedule, hooks, resume, args=(buckets,), mesh=mesh,
                         pass_iteration=annealed)
  return hierarchy, {"capacity": list(capacity), "losses": progress.losses, "best_iteration": progress.best_iteration,
                     "validation": progress.best_score, "seconds": time.time() - start}
