"""One level's Expectation–Gradient objective (paper §4.2): the lattice's inputs from the level's networks,
the loss over a batch of level views, and decoding of weak views.

Level i's loss on its views is −(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N, each term the
lattice's exact log-likelihood (strong views through `annotate`). Below the root level, a root network (MLP
or LSTM over the view's observations) stands in for the untrained levels above; the root level is the
lattice's top-level mode (one procedure, called once). An optional call penalty λ is a prior on the latent
call sequence: the root's log η_⊥ drops by λ at every push, so weak views' posteriors favour fewer, longer
calls (a strong view's log-likelihood drops by λ per call, a constant).
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import lattice, views
from php_jax.model import PHPLevel

DECODERS = ("sample", "viterbi", "max_marginal")


class LevelModel(nnx.Module):
  """What one level trains: its PHP networks, and a root network unless it is the root level. call_penalty
  (not trained) is subtracted from the root network's log η_⊥ at every push (`lattice_inputs`)."""

  def __init__(self, php: PHPLevel, root: nnx.Module | None, call_penalty: float = 0.0):
    self.php = php
    self.root = root
    self.call_penalty = call_penalty


def lattice_inputs(model: LevelModel, observations, actions, procedures, counters, length, capacity: int,
                   used_capacity=None):
  """One view → the lattice's inputs, annotated where procedures/counters are known.

  observations [T+1, D], actions [T, F], procedures/counters [T] (UNKNOWN = −1), length [] →
  (log_root [T, K], log_op, log_stop, log_cont [T, K, C]). With used_capacity [] int (≤ capacity), counters
  ≥ used_capacity are masked out: the same lattice as with capacity = used_capacity, padded (seeds of
  different capacities trained as one program, `php_jax.seeds`).
  """
  tau = jnp.arange(capacity, dtype=jnp.float32)
  log_op = model.php.log_op(observations[:-1], tau, actions)
  z = model.php.termination_logits(observations[1:], tau)
  log_stop, log_cont = jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)
  if used_capacity is not None:
    log_op = jnp.where(tau < used_capacity, log_op, -jnp.inf)
    log_cont = jnp.where(tau + 1 < used_capacity, log_cont, -jnp.inf)
  if model.root is None:  # the root level: one procedure, called once
    log_root = jnp.zeros(log_op.shape[:2], log_op.dtype)
    log_stop = lattice.top_level(log_stop, length)
  else:
    log_root = model.root(observations[:-1]) - model.call_penalty
  return log_root, lattice.annotate(log_op, procedures, counters), log_stop, log_cont


def view_log_likelihoods(model: LevelModel, batch: views.LevelView, capacity: int,
                         used_capacity=None) -> jax.Array:
  """[B] log P(ζ, ξ) for annotated views, log P(ξ) for the others."""
  def one(obs, act, proc, tau, n):
    return lattice.forward_backward(*lattice_inputs(model, obs, act, proc, tau, n, capacity, used_capacity),
                                    length=n).log_likelihood
  return jax.vmap(one)(batch.observations, batch.actions, batch.procedures, batch.counters, batch.length)


def level_loss(model: LevelModel, buckets: list[views.LevelView], capacity: int, strong_weight: float,
               used_capacity=None) -> jax.Array:
  """−(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N over the real views of every length bucket (the
  copies that pad a bucket weigh 0 and are not counted in N). used_capacity: as in `lattice_inputs`."""
  total, count = 0.0, 0
  for batch in buckets:
    weights = jnp.where(batch.real, jnp.where(batch.strong, strong_weight, 1.0), 0.0)
    total = total - jnp.sum(weights * view_log_likelihoods(model, batch, capacity, used_capacity))
    count = count + jnp.sum(batch.real)
  return total / count


def decode(model: LevelModel, view: views.LevelView, capacity: int, method: str, key: jax.Array):
  """Each view's most likely / sampled frames at this level (method in DECODERS): (procedures, counters)
  [B, T] numpy."""
  batch = views.device_view(view)

  def one(obs, act, proc, tau, n, k):
    inputs = lattice_inputs(model, obs, act, proc, tau, n, capacity)
    if method == "viterbi":
      return lattice.viterbi(*inputs, length=n)
    if method == "sample":
      return lattice.sample_posterior(k, *inputs, length=n)
    return lattice.max_marginal_path(lattice.forward_backward(*inputs, length=n), length=n)

  keys = jax.random.split(key, view.length.shape[0])
  paths = jax.jit(jax.vmap(one))(batch.observations, batch.actions, batch.procedures, batch.counters,
                                 batch.length, keys)
  return np.asarray(paths.procedure), np.asarray(paths.counter)
