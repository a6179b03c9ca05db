"""Joint Expectation–Gradient training: every level at once, with the hierarchy's own root (no stand-in).

The loss is −(w_strong Σ_annotated log P(ζ_known, ξ) + Σ_weak log P(ξ)) / N, each term the exact
log-likelihood of a demonstration's elementary actions under the whole hierarchy, summed over every call
stack that agrees with its (complete, partial or absent) annotation (`stack_lattice`); its gradient is the
EG gradient of every level's networks at once. Demonstrations are batched by length into buckets.
"""
from __future__ import annotations

import math
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh

from php_jax import call_graph, checkpoint, fitting, sharding, stack_lattice, train, views
from php_jax.decoding import stack_inputs
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy


def joint_capacity(demos: Demonstration, spec: HierarchySpec, config: train.TrainConfig) -> tuple[int, ...]:
  """Counter capacity per level, root first. Below the root: the longest annotated call (config.capacity
  when nothing is annotated), at least config.min_capacity. The root: its most annotated operations, scaled
  by how much longer the longest demonstration is than the longest annotated one (weak demonstrations may
  need more root operations), or config.capacity when nothing is annotated; at least config.min_capacity[0]."""
  taus, strong = np.asarray(demos.counters), np.asarray(demos.strong)
  lengths = np.asarray(demos.length)
  capacity = []
  for level in range(spec.num_levels):
    annotated = taus[strong][..., level]
    annotated = annotated[annotated != UNKNOWN]
    needed = int(annotated.max()) + 1 if annotated.size else config.capacity
    if level == 0 and annotated.size:
      needed = math.ceil(needed * lengths.max() / lengths[strong].max())
    least = config.min_capacity[level] if config.min_capacity else 0
    capacity.append(max(needed, least))
  return tuple(capacity)


def _buckets(demos: Demonstration, num_buckets: int,
             mesh: Mesh | None = None) -> list[tuple[Demonstration, jax.Array]]:
  """Demonstrations sorted by length into up to num_buckets groups, each trimmed to its longest, as device
  arrays with the annotation kept only on strong ones; each with real [B] bool. With a mesh, each group is
  padded to a multiple of its device count (`sharding.pad`: real False on the copies) and split over its
  devices along B."""
  arrays = [np.asarray(x) for x in demos]
  strong = np.asarray(demos.strong)[:, None, None]
  buckets = []
  for group, width in views.length_groups(np.asarray(demos.length), num_buckets):
    obs, act, procs, taus, length, is_strong = (x[group] for x in arrays)
    batch, real = sharding.pad(Demonstration(
        obs[:, :width + 1], act[:, :width], np.where(strong[group], procs, UNKNOWN)[:, :width],
        np.where(strong[group], taus, UNKNOWN)[:, :width], length, is_strong), mesh)
    buckets.append(sharding.put((batch, real), mesh))
  return buckets


def log_likelihoods(hierarchy: PHPHierarchy, batch: Demonstration, capacity: tuple[int, ...]) -> jax.Array:
  """[B] log P(ζ_known, ξ) of each demonstration of batch under the whole hierarchy."""
  def one(obs, act, procs, taus, n):
    inputs = stack_inputs(hierarchy, capacity, obs, act, n)
    return stack_lattice.log_likelihood(inputs, procs, taus)
  return jax.vmap(one)(batch.observations, batch.actions, batch.procedures, batch.counters, batch.length)


def joint_loss(hierarchy: PHPHierarchy, buckets: list[tuple[Demonstration, jax.Array]], capacity: tuple[int, ...],
               strong_weight: float) -> jax.Array:
  """−(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N over the real demonstrations of every bucket
  (batch, real) (the copies that pad a bucket split over devices weigh 0 and are not counted in N)."""
  total, count = 0.0, 0
  for batch, real in buckets:
    weights = jnp.where(real, jnp.where(batch.strong, strong_weight, 1.0), 0.0)
    total = total - jnp.sum(weights * log_likelihoods(hierarchy, batch, capacity))
    count = count + jnp.sum(real)
  return total / count


def train_joint(spec: HierarchySpec, demos: Demonstration, config: train.TrainConfig,
                validate: Callable[[PHPHierarchy], float] | None = None, log: Callable[[dict], None] = print,
                checkpoint_path: str | None = None) -> tuple[PHPHierarchy, dict]:
  """Trains every level together for config.iterations Adam iterations, keeping the snapshot with the best
  validate(hierarchy) (config.snapshot's rule). Checkpoints and resumes as train.train_hierarchy does
  (the same log protocol); a checkpoint made with other settings raises CheckpointError. Returns the
  hierarchy and a report {capacity, losses, best_iteration, validation, seconds}."""
  config = train.prepare(spec, demos, config)
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
  progress = fitting.fit(hierarchy, lambda h, buckets: joint_loss(h, buckets, capacity, config.strong_weight),
                         config.iterations, config.learning_rate, config.eval_every,
                         (lambda it, loss: validate(hierarchy)) if validate else None, counted_log, resume,
                         save if checkpoint_path else None, config.snapshot, args=(buckets,), mesh=mesh)
  return hierarchy, {"capacity": list(capacity), "losses": progress.losses, "best_iteration": progress.best_iteration,
                     "validation": progress.best_score, "seconds": time.time() - start}
