"""The Expectation–Gradient objective (paper §4.2) of both training modes: the lattices' inputs from the
networks, their counter capacities, the weighted negative log-likelihood, and decoding of weak level views.

The loss is −(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N, each term an exact log-likelihood:
- level-wise (`level_loss`), of one level's views under the two-level lattice (`lattice`; strong views through
  `annotate`). Below the root level, a root network (MLP or LSTM over the view's observations) stands in for
  the untrained levels above; the root level is the lattice's top-level mode (one procedure, called once). An
  optional call penalty λ is a prior on the latent call sequence: the root's log η_⊥ drops by λ at every push,
  so weak views' posteriors favour fewer, longer calls (a strong view's log-likelihood drops by λ per call, a
  constant);
- jointly (`stack_loss`), of the demonstrations' elementary actions under the whole hierarchy, summed over
  every call stack that agrees with their (complete, partial or absent) annotation (`stack_lattice`);
  optionally tempered (deterministic annealing, `annealed_temperature`): −T log Σ_ζ P(ζ, ξ)^(1/T), whose
  gradient takes the EG expectation under the flatter P(ζ | ξ)^(1/T); optionally with the call penalty too,
  λ_i off every call of a level-i procedure.
"""
from __future__ import annotations

import functools
import math
from typing import Any, Callable, Iterable

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax.data import views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.inference import lattice, stack_lattice
from php_jax.model import PHPHierarchy, PHPLevel

DECODERS = ("sample", "viterbi", "max_marginal")


class LevelModel(nnx.Module):
  """What one level trains: its PHP networks, and a root network unless it is the root level. call_penalty
  (not trained) is subtracted from the root network's log η_⊥ at every push (`lattice_inputs`)."""

  def __init__(self, php: PHPLevel, root: nnx.Module | None, call_penalty: float = 0.0):
    self.php = php
    self.root = root
    self.call_penalty = call_penalty


def lattice_inputs(model: LevelModel, view: views.LevelView, capacity: int, used_capacity=None):
  """One view (a LevelView without its batch axis: observations [T+1, D], actions [T, F], procedures and
  counters [T] (UNKNOWN = −1), length []) → the lattice's inputs, annotated where procedures/counters are
  known: LatticeInputs(log_root [T, K], log_op, log_stop, log_cont [T, K, C], length), the one object every
  E-step function takes. With used_capacity [] int (≤ capacity),
  counters ≥ used_capacity are masked out: the same lattice as with capacity = used_capacity, padded (seeds
  of different capacities trained as one program, `levelwise.train_seeds`).
  """
  observations, actions, length = view.observations, view.actions, view.length
  if model.php.history is not None:
    raise ValueError("a level with a memory is trained jointly: its history reads every elementary step, which "
                     "a level's view of the steps leaves out")
  tau = jnp.arange(capacity, dtype=jnp.float32)
  features = model.php.encode(observations)  # once per observation, for every procedure and counter
  log_op = model.php.log_op(features[:-1], tau, actions)
  log_stop, log_cont = model.php.stop_log_probs(features[1:], tau, length)
  if used_capacity is not None:
    log_op = jnp.where(tau < used_capacity, log_op, -jnp.inf)
    log_cont = jnp.where(tau + 1 < used_capacity, log_cont, -jnp.inf)
  if model.root is None:  # the root level: one procedure, called once
    log_root = jnp.zeros(log_op.shape[:2], log_op.dtype)
    log_stop = lattice.top_level(log_stop, length)
  else:
    log_root = model.root(observations[:-1]) - model.call_penalty
  return lattice.LatticeInputs(log_root, lattice.annotate(log_op, view.procedures, view.counters), log_stop,
                               log_cont, length)


def view_log_likelihoods(model: LevelModel, batch: views.LevelView, capacity: int,
                         used_capacity=None) -> jax.Array:
  """[B] log P(ζ, ξ) for annotated views, log P(ξ) for the others."""
  def one(view):
    return lattice.forward_backward(lattice_inputs(model, view, capacity, used_capacity)).log_likelihood
  return jax.vmap(one)(batch)


def level_loss(model: LevelModel, buckets: list[views.LevelView], capacity: int, strong_weight: float,
               used_capacity=None) -> jax.Array:
  """[] weighted negative log-likelihood of the real views of every length bucket (`weighted_nll`).
  used_capacity: as in `lattice_inputs`."""
  return weighted_nll(((view_log_likelihoods(model, batch, capacity, used_capacity), batch.real, batch.strong)
                       for batch in buckets), strong_weight)


def stack_inputs(hierarchy: PHPHierarchy, capacity: tuple[int, ...], observations: jax.Array, actions: jax.Array,
                 length: jax.Array, call_penalty: tuple[float, ...] | None = None) -> stack_lattice.StackInputs:
  """The whole-stack lattice's inputs from the networks of every level, for one demonstration.

  observations [T+1, D], actions [T, F], length [], capacity per level (root first) → StackInputs (level i:
  log_call [T, K_i, C_i, K_{i+1}] for i < d−1, log_act [T, K_{d−1}, C_{d−1}], log_stop / log_cont [T, K_i, C_i]).
  call_penalty (per level, root first): λ_{i+1} is subtracted from every log_call of level i, a prior cost of
  each call of a level-(i+1) procedure (λ_0, the root's, is not used: the root is called once).
  """
  depth = len(hierarchy.levels)
  log_call, log_stop, log_cont = [], [], []
  for level, php in enumerate(hierarchy.levels):
    tau = jnp.arange(capacity[level], dtype=jnp.float32)
    features = php.features(observations, actions)  # once per step, for every procedure and counter
    if level < depth - 1:
      penalty = call_penalty[level + 1] if call_penalty else 0.0
      log_call.append(php.op_log_probs(features[:-1], tau)[0] - penalty)
    else:
      log_act = php.log_op(features[:-1], tau, actions)
    stop, cont = php.stop_log_probs(features[1:], tau, length)
    log_stop.append(stop)
    log_cont.append(cont)
  return stack_lattice.StackInputs(tuple(log_call), log_act, tuple(log_stop), tuple(log_cont), length)


def stack_query(hierarchy: PHPHierarchy, capacity: tuple[int, ...], query: Callable[[stack_lattice.StackInputs], Any],
                observations: jax.Array, actions: jax.Array, length: jax.Array) -> Any:
  """query(stack_inputs(...)) of each demonstration (observations [B, T+1, D], actions [B, T, F], length [B]),
  vmapped: a pytree of [B, ...] arrays. Compiled once per architecture, capacity, query (a function defined
  once, such as a module's) and shape, whichever hierarchy object of that architecture is asked."""
  return _stack_query(nnx.graphdef(hierarchy), nnx.state(hierarchy), tuple(capacity), query, observations, actions,
                      length)


@functools.partial(jax.jit, static_argnums=(0, 2, 3))
def _stack_query(graphdef: nnx.GraphDef, state: nnx.State, capacity: tuple[int, ...], query, observations, actions,
                 length):
  hierarchy = nnx.merge(graphdef, state)
  return jax.vmap(lambda obs, act, n: query(stack_inputs(hierarchy, capacity, obs, act, n)))(
      observations, actions, length)


CHUNK = 64  # demonstrations whose log-likelihoods one compiled call of `demonstration_log_likelihoods` computes


def demonstration_log_likelihoods(hierarchy: PHPHierarchy, capacity: tuple[int, ...],
                                  demos: Demonstration) -> np.ndarray:
  """[B] float64 log P(actions | observations) of each of demos under the whole hierarchy, the annotation
  unused: −inf where no call stack within capacity and the hierarchy's call graph explains it (whatever the
  weights). CHUNK at a time, the last chunk padded with copies of the last demonstration, so that one compiled
  program serves every chunk."""
  num = len(demos.length)
  size = min(CHUNK, num)
  out = []
  for start in range(0, num, size):
    part = views.select(demos, np.minimum(np.arange(start, start + size), num - 1))
    out.append(np.asarray(jax.device_get(stack_query(hierarchy, capacity, stack_lattice.log_likelihood,
                                                     part.observations, part.actions, part.length))))
  return np.concatenate(out)[:num].astype(np.float64)


def stack_log_likelihoods(hierarchy: PHPHierarchy, batch: Demonstration, capacity: tuple[int, ...],
                          temperature=1.0, call_penalty: tuple[float, ...] | None = None) -> jax.Array:
  """[B] log P(ζ_known, ξ) of each demonstration of batch under the whole hierarchy; with a posterior
  temperature T [], its tempered form T · log Σ P(ζ, ξ)^(1/T) (`stack_lattice.log_likelihood`); with a
  call_penalty (`stack_inputs`), each stack's probability times its prior exp(−Σ λ · calls)."""
  def one(obs, act, procs, taus, n):
    inputs = stack_inputs(hierarchy, capacity, obs, act, n, call_penalty)
    return stack_lattice.log_likelihood(inputs, procs, taus, temperature)
  return jax.vmap(one)(batch.observations, batch.actions, batch.procedures, batch.counters, batch.length)


def stack_loss(hierarchy: PHPHierarchy, buckets: list[tuple[Demonstration, jax.Array]], capacity: tuple[int, ...],
               strong_weight: float, temperature=1.0, call_penalty: tuple[float, ...] | None = None) -> jax.Array:
  """[] weighted negative log-likelihood (`weighted_nll`) of the real demonstrations of every bucket
  (batch, real [B]) under the whole hierarchy, tempered at a posterior temperature [] other than 1, with a
  prior cost per call (`stack_inputs`) where call_penalty is given."""
  return weighted_nll(((stack_log_likelihoods(hierarchy, batch, capacity, temperature, call_penalty), real,
                        batch.strong) for batch, real in buckets), strong_weight)


def annealed_temperature(start: float, iteration: jax.Array, iterations: int) -> jax.Array:
  """[] the posterior temperature after `iteration` updates of `iterations` (deterministic annealing): start
  at the first, falling linearly to 1 at half the iterations, 1 from there on."""
  ramp = max(iterations // 2, 1)
  return 1.0 + (start - 1.0) * jnp.clip(1.0 - iteration / ramp, 0.0, 1.0)


def weighted_nll(terms: Iterable[tuple[jax.Array, jax.Array, jax.Array]], strong_weight: float) -> jax.Array:
  """−(w_strong Σ_strong log P + Σ_weak log P) / N over every (log_likelihoods, real, strong) [B] of terms: the
  copies that pad a batch (real False) weigh 0 and are not counted in N."""
  total, count = 0.0, 0
  for log_likelihoods, real, strong in terms:
    weights = jnp.where(real, jnp.where(strong, strong_weight, 1.0), 0.0)
    total = total - jnp.sum(weights * log_likelihoods)
    count = count + jnp.sum(real)
  return total / count


def counter_capacity(annotated: np.ndarray, default: int, least: int = 0, longest: int = 1,
                     longest_annotated: int = 1) -> int:
  """The counter capacity C of one level: its longest annotated call (annotated: its annotated counters, any
  shape, UNKNOWN skipped) scaled by longest / longest_annotated, or `default` when nothing is annotated; at
  least `least`. The networks are evaluated on every counter cell, so C is kept as small as the calls allow."""
  annotated = np.asarray(annotated)[np.asarray(annotated) != UNKNOWN]
  needed = math.ceil((int(annotated.max()) + 1) * longest / longest_annotated) if annotated.size else default
  return max(needed, least)


def decode(model: LevelModel, view: views.LevelView, capacity: int, method: str, key: jax.Array):
  """Each view's most likely / sampled frames at this level (method in DECODERS): (procedures, counters)
  [B, T] numpy."""
  batch = views.device_view(view)

  def one(view, k):
    inputs = lattice_inputs(model, view, capacity)
    if method == "viterbi":
      return lattice.viterbi(inputs)
    if method == "sample":
      return lattice.sample_posterior(k, inputs)
    return lattice.max_marginal_path(lattice.forward_backward(inputs), length=inputs.length)

  keys = jax.random.split(key, view.length.shape[0])
  paths = jax.jit(jax.vmap(one))(batch, keys)
  return np.asarray(paths.procedures), np.asarray(paths.counters)
