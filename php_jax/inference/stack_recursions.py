"""The whole-stack lattice's recursions (`php_jax.inference.stack_lattice`, whose docstring describes them):
the annotation as potentials, the forward pass as one lax.scan renormalised every step (sum-product, or
max-product with backpointers), the backtrack through those backpointers, the k-best forward pass, and the event
posteriors behind the entropies. Inputs are a StackInputs, checked by the public functions."""
from __future__ import annotations

import jax
import jax.numpy as jnp

from php_jax.inference.lattice_inputs import NO_FRAME


def annotation_potentials(inputs, procedures, counters):
  """Per-level log-potentials [T, K_i, C_i]: 0 where the frame agrees with the annotation, −inf elsewhere.

  procedures, counters: [T, d] int or None; −1 is unknown, any other value outside 0..K_i−1 matches nothing."""
  num_steps, dtype = inputs.log_act.shape[0], inputs.log_act.dtype
  unknown = jnp.full((num_steps, len(inputs.log_stop)), -1, jnp.int32)
  procedures = unknown if procedures is None else jnp.asarray(procedures)
  counters = unknown if counters is None else jnp.asarray(counters)
  potentials = []
  for i, stop in enumerate(inputs.log_stop):
    _, size, capacity = stop.shape
    proc_ok = (procedures[:, i, None] < 0) | (procedures[:, i, None] == jnp.arange(size))
    tau_ok = (counters[:, i, None] < 0) | (counters[:, i, None] == jnp.arange(capacity))
    potentials.append(jnp.where(proc_ok[:, :, None] & tau_ok[:, None, :], 0.0, -jnp.inf).astype(dtype))
  return tuple(potentials)


def finite_or_zero(x):
  return jnp.where(jnp.isfinite(x), x, 0.0)


def logsumexp(x):
  """logsumexp over the last axis; −inf (value and zero gradient, no NaN) where every entry is −inf; NaN where
  an entry is."""
  peak = jax.lax.stop_gradient(finite_or_zero(jnp.max(x, axis=-1)))
  total = jnp.sum(jnp.exp(x - peak[..., None]), axis=-1)
  empty = total == 0
  return jnp.where(empty, -jnp.inf, jnp.log(jnp.where(empty, 1.0, total)) + peak)


def descend(fresh, carry: tuple, scale, inputs, potentials, t):
  """The mass of every stack at step t, before any frame stops: the root's frames (fresh: the new root's
  [..., 1, 1] mass, beside the continuing ones, carry[0] − scale) pushed down level by level with log_call[i][t],
  each level's continuing frames (carry[i + 1] − scale) beside the pushed ones, plus step t's potentials and the
  action's log-probability. [..., K_0, C_0, ..., K_{d-1}, C_{d-1}] (top_k's leading k in the ...)."""
  log_call, log_act = inputs.log_call, inputs.log_act
  depth = len(carry)
  alpha = jnp.concatenate([fresh, carry[0] - scale], axis=-1)
  potential = potentials[0][t]  # over levels 0..d-2, added to every frame of step t in one pass
  for i in range(depth - 1):
    pushed = alpha[..., None] + log_call[i][t]
    alpha = jnp.concatenate([pushed[..., None], carry[i + 1] - scale], axis=-1)
    if i + 1 < depth - 1:
      potential = potential[..., None, None] + potentials[i + 1][t]
  return alpha + potential[..., None, None] + (log_act[t] + potentials[-1][t])


def rescaled(conts: list, mass, t, length, dtype):
  """(scale: the largest finite continuing mass, which the next step subtracts; step t's log-increment: the
  scale before the last step, the remaining mass at it, 0 on padding)."""
  peaks = [jnp.max(c) for c in conts if c.size]
  scale = jax.lax.stop_gradient(finite_or_zero(jnp.max(jnp.stack(peaks)) if peaks else jnp.zeros((), dtype)))
  return scale, jnp.where(t == length - 1, mass, jnp.where(t < length - 1, scale, 0.0))


def forward(inputs, potentials, length, semiring_max=False, keep_stops=False):
  """The forward recursion (php_jax.inference.stack_lattice's docstring) as one lax.scan, carry renormalised every step.

  The carry is the continuing mass cont_i (τ_i < C_i − 1) of every level and its maximum, the step's scale,
  which the next step subtracts as it reads the carry (one pass fewer than renormalising in place); step t
  pushes with log_call[·][t] itself. The carry runs on through padding, where increments are 0.

  Returns:
    log_increments: [T] summing to log P(ξ) (max-product: the best path's log-probability).
    stops: per level i, [T, K_0, C_0, ..., K_i, C_i] the stop scores m_i + log_stop_i (keep_stops), or
      max-product [T, K_0, C_0, ..., K_{i-1}, C_{i-1}] int32 the best stopped frame of level i, flat h·C_i + τ
      (backpointers); None for a sum-product pass without keep_stops.
  """
  _, log_act, log_stop, log_cont, _ = inputs
  depth, dtype = len(log_stop), log_act.dtype

  def step(carry, t):
    carry, scale = carry
    fresh = jnp.where(t == 0, 0.0, -jnp.inf).astype(dtype)[None, None]
    mass = descend(fresh, carry, scale, inputs, potentials, t)
    conts, stops = [], []
    for i in reversed(range(depth)):
      conts.insert(0, mass[..., :-1] + log_cont[i][t, :, :-1])
      scores = mass + log_stop[i][t]
      flat = scores.reshape(scores.shape[:-2] + (-1,))
      if semiring_max:
        mass = jnp.max(flat, axis=-1)  # the first maximiser by a min-reduction: much faster than argmax on CPU
        cells = jnp.arange(flat.shape[-1], dtype=jnp.int32)
        stops.insert(0, jnp.min(jnp.where(flat == mass[..., None], cells, flat.shape[-1]), axis=-1))
      else:
        stops.insert(0, scores)
        mass = logsumexp(flat)
    scale, increment = rescaled(conts, mass, t, length, dtype)
    outputs = tuple(stops) if semiring_max or keep_stops else None
    return (tuple(conts), scale), (increment, outputs)

  init = tuple(jnp.full(prefix_shape(log_stop, i)[:-1] + (log_stop[i].shape[2] - 1,), -jnp.inf, dtype)
               for i in range(depth))
  init = (init, jnp.zeros((), dtype))
  _, (log_increments, stops) = jax.lax.scan(step, init, jnp.arange(log_act.shape[0]))
  return log_increments, stops


def prefix_shape(log_stop, level):
  """(K_0, C_0, ..., K_level, C_level)."""
  return tuple(n for x in log_stop[:level + 1] for n in x.shape[1:])


def evidence(inputs, potentials, length):
  """[] log P(ξ) summed over every path the potentials allow (the forward pass's increments)."""
  return jnp.sum(forward(inputs, potentials, length)[0])


def backtrack(stops, length, capacities, choose, dtype, rank=0):
  """Reverse scan from the last step: the frames of step t given step t+1's and step t's stop tables.

  Levels 0..j (j the deepest level with τ > 0 at t+1, −1 after the last step) are kept, τ_j one less; the
  stopped levels j+1..d-1 are chosen top-down by choose(level, table at the chosen prefix, rank, t) → (flat
  h·C + τ, log-probability of that choice, of the given dtype, rank). The rank (top_k's: which of a prefix's
  k best partial paths) starts at `rank` after the last step and passes from each choice to the next.
  Returns (procedures [T, d], counters [T, d]) with NO_FRAME on padding, and [] the sum of the choices'
  log-probabilities.
  """
  depth = len(capacities)

  def step(state_next, xs):
    t, tables = xs
    procs_next, taus_next, rank_next, log_prob = state_next
    used = t < length
    resumed = taus_next > 0
    deepest = jnp.where((t < length - 1) & jnp.any(resumed), depth - 1 - jnp.argmax(resumed[::-1]), -1)
    procs, taus, rank = [], [], rank_next
    for i in range(depth):
      index, log_choice, chosen_rank = choose(i, tables[i][tuple(x for frame in zip(procs, taus) for x in frame)],
                                              rank, t)
      h, tau = jnp.divmod(index, capacities[i])
      procs.append(jnp.where(i <= deepest, procs_next[i], h))
      taus.append(jnp.where(i <= deepest, taus_next[i] - (i == deepest), tau))
      rank = jnp.where(i <= deepest, rank, chosen_rank)
      log_prob = log_prob + jnp.where(used & (i > deepest), log_choice, 0.0)
    procs, taus = (jnp.where(used, jnp.stack(x).astype(jnp.int32), x_next)
                   for x, x_next in ((procs, procs_next), (taus, taus_next)))
    rank = jnp.where(used, rank, rank_next)
    return (procs, taus, rank, log_prob), (jnp.where(used, procs, NO_FRAME), jnp.where(used, taus, NO_FRAME))

  init = (jnp.zeros(depth, jnp.int32), jnp.zeros(depth, jnp.int32), jnp.asarray(rank, jnp.int32),
          jnp.zeros((), dtype))
  num_steps = jax.tree.leaves(stops)[0].shape[0]
  (_, _, _, log_prob), (procedures, counters) = jax.lax.scan(step, init, (jnp.arange(num_steps), stops),
                                                             reverse=True)
  return procedures, counters, log_prob


def forward_top_k(k: int, inputs, potentials, length):
  """forward's max-product recursion with the k best partial paths of every prefix (a leading axis k, each
  list descending): a merge over stopped frames keeps the k best of (frame, rank) candidates; every other step
  adds log-factors and keeps the ranks.

  Returns:
    log_prob: [k] of the k best paths, descending.
    pointers: per level i, [T, K_0, C_0, ..., K_{i-1}, C_{i-1}, k] int32 the flat (h·C_i + τ)·k + rank of the
      stopped level-i frame and its rank behind each of the prefix's k best.
  """
  _, log_act, log_stop, log_cont, _ = inputs
  depth, dtype = len(log_stop), log_act.dtype
  first = jnp.full(k, -jnp.inf, dtype).at[0].set(0.0)

  def step(carry, t):
    carry, scale = carry
    mass = descend(jnp.where(t == 0, first, -jnp.inf)[:, None, None], carry, scale, inputs, potentials, t)
    conts, pointers = [], []
    for i in reversed(range(depth)):
      conts.insert(0, mass[..., :-1] + log_cont[i][t, :, :-1])
      candidates = jnp.moveaxis(mass + log_stop[i][t], 0, -1)  # [..., K_i, C_i, k]
      best, pointer = jax.lax.top_k(candidates.reshape(candidates.shape[:-3] + (-1,)), k)
      pointers.insert(0, pointer.astype(jnp.int32))
      mass = jnp.moveaxis(best, -1, 0)
    scale, increment = rescaled(conts, mass, t, length, dtype)
    return (tuple(conts), scale), (increment, tuple(pointers))

  init = tuple(jnp.full((k,) + prefix_shape(log_stop, i)[:-1] + (log_stop[i].shape[2] - 1,), -jnp.inf, dtype)
               for i in range(depth))
  _, (log_increments, pointers) = jax.lax.scan(step, (init, jnp.zeros((), dtype)), jnp.arange(log_act.shape[0]))
  return jnp.sum(log_increments, axis=0), pointers


def expected_log_joint(events, log_factors):
  """Σ P(event) · log-factor over matching leaves: E[log P'(ζ, ξ)] of the lattice of log_factors under the
  posterior whose event probabilities are `events` (log P(ζ, ξ) is a sum of one input entry per event).
  Events of probability zero count 0 even where the log-factor is −inf. Returns []."""
  total = 0.0
  for prob, log_factor in zip(jax.tree.leaves(events), jax.tree.leaves(log_factors)):
    used = prob > 0
    total = total + jnp.sum(jnp.where(used, prob * jnp.where(used, log_factor, 0.0), 0.0))
  return total


def entropy_and_events(p, potentials, length):
  """(H(p), the posterior of every event: jax.grad of log P(ξ) w.r.t. the inputs and potentials, log P(ξ)).
  Where no path explains ξ, H(p) is 0 (a sum over no paths) and every event's posterior 0."""
  log_z, events = jax.value_and_grad(evidence, argnums=(0, 1))(p, potentials, length)
  explained = jnp.isfinite(log_z)
  entropy = jnp.where(explained, log_z, 0.0) - expected_log_joint(events, (p, potentials))
  return jnp.where(explained, entropy, 0.0), events, log_z
