"""More operations on the E-step's lattice (inputs and path semantics as in php_jax.inference.lattice): the k most
likely paths, KL divergence and cross-entropy between two posteriors, a differentiable posterior sample and
the online forward filter, and `TwoLevelLattice`, the lattice as one structure answering every query. Each is
exact and checked against enumeration of every path in the tests. Argument conventions, refusals and dtypes
as in php_jax.inference.lattice: one LatticeInputs may stand for the five arrays, annotations are `procedures`,
`counters` [T], float16 and bfloat16 inputs are computed in float32 (results float32, gradients in the
inputs' dtype)."""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp

from php_jax.inference.lattice import (_entropy, _expected_log_joint, _finite_or_zero, _is_push, _path_from_states,
                                       _shift, forward_backward, posterior_entropy, sample_posterior, viterbi)
from php_jax.inference.lattice_inputs import (NO_FRAME, LatticeInputs, LatticePath, LatticePosterior,
                                              LatticeStructure, accepts_inputs, annotated_log_op, as_inputs,
                                              check_annotation, check_inputs, check_k, check_key, check_temperature,
                                              in_common_dtype, no_frame_unless_explained)
from php_jax.inference.stack_recursions import logsumexp


@accepts_inputs
def top_k(k: int, log_root, log_op, log_stop, log_cont, length=None, procedures=None, counters=None) -> LatticePath:
  """The k most likely latent paths, best first (k-best max-product: each cell keeps its k best partial
  paths, and the push cells of step t the k best stops of step t−1, with one backpointer each).

  If fewer than k paths are possible, the remaining entries have log_prob −inf and procedure = counter =
  NO_FRAME at every step. Ties are broken deterministically (by the order of the candidates' flat indices).

  Args:
    k: int ≥ 1 (static).
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the five).
  Returns:
    LatticePath(procedures [k, T], counters [k, T], log_prob [k]), log_prob descending; entry 0 is viterbi's.
  Example:
    >>> best = top_k(3, log_root, log_op, log_stop, log_cont, length=5)
    >>> best.log_prob  # [3] log P(ζ, ξ) of the three most likely paths
  """
  k = check_k(k)
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = annotated_log_op(log_op, procedures, counters, length)
  return _top_k(k, *in_common_dtype(log_root, log_op, log_stop, log_cont), length)


@functools.partial(jax.jit, static_argnums=0)
def _top_k(k, log_root, log_op, log_stop, log_cont, length):
  num_steps, num_procs, capacity = log_op.shape
  num_cells = num_procs * capacity
  is_push = _is_push(num_procs, capacity)
  can_continue = jnp.arange(num_cells) % capacity < capacity - 1
  op_stop = (log_op + log_stop).reshape(num_steps, -1)
  op_cont = jnp.where(can_continue, (log_op + log_cont).reshape(num_steps, -1), -jnp.inf)

  def step(carry, t):
    # continuing [k, S]: rank r's partial score per cell; pending [k]: the k best stops of step t−1. Both
    # are relative to the running scale, as in lattice._forward_scan.
    continuing, pending = carry
    pushed = jnp.repeat(log_root[t], capacity)[None, :] + pending[:, None]
    alpha = jnp.where(is_push, pushed, continuing)
    stop_scores, stops = jax.lax.top_k((alpha + op_stop[t]).reshape(-1), k)  # flat index rank·S + cell
    cont_scores = alpha + op_cont[t]
    scale = _finite_or_zero(jnp.maximum(jnp.max(cont_scores), stop_scores[0]))
    carry = (_shift(cont_scores, 1, -jnp.inf) - scale, stop_scores - scale)
    return carry, (jnp.where(t < length - 1, scale, 0.0), stop_scores, stops.astype(jnp.int32))

  init = (jnp.full((k, num_cells), -jnp.inf, log_op.dtype),
          jnp.full(k, -jnp.inf, log_op.dtype).at[0].set(0.0))
  _, (scales, stop_scores, stops) = jax.lax.scan(step, init, jnp.arange(num_steps))
  log_prob = jnp.sum(scales) + stop_scores[length - 1]

  def backtrack(state_next, xs):  # state: [k] flat rank·S + cell of each of the k paths
    t, best = xs
    continued = state_next % capacity > 0  # then the predecessor is the same rank, one cell down
    state = jnp.where(t == length - 1, best, jnp.where(continued, state_next - 1, best[state_next // num_cells]))
    state = jnp.where(t < length, state, state_next)
    return state, jnp.where(t < length, state % num_cells, NO_FRAME)

  _, cells = jax.lax.scan(backtrack, jnp.zeros(k, jnp.int32), (jnp.arange(num_steps), stops), reverse=True)
  return _path_from_states(*no_frame_unless_explained(log_prob[:, None], cells.T), capacity, log_prob)


def cross_entropy(p: LatticeInputs, q: LatticeInputs):
  """H(p, q) = −Σ_ζ p(ζ | ξ) log q(ζ | ξ) in nats, between the posteriors over latent paths of two lattices
  of the same shape and length: log P_q(ξ) − E_p[log P_q(ζ, ξ)], exact from p's marginals. +inf where q
  rules out a path p allows; 0 where p allows no path (a sum over no paths). Differentiable w.r.t. both p
  and q.

  Args:
    p, q: LatticeInputs with the same [T, K] / [T, K, C] shapes and length (checked when concrete).
      TwoLevelLattice(p, ...).cross_entropy(TwoLevelLattice(q, ...)) restricts either to an annotation.
  Returns:
    [] cross-entropy.
  Example:
    >>> cross_entropy(LatticeInputs(*inputs, 5), LatticeInputs(*other_inputs, 5))
  """
  p, q = _same_lattice(p, q)
  return _cross_entropy(forward_backward(*p), q)


def kl_divergence(p: LatticeInputs, q: LatticeInputs):
  """KL(p ‖ q) = Σ_ζ p(ζ | ξ) (log p(ζ | ξ) − log q(ζ | ξ)) in nats between the posteriors over latent paths
  (= cross_entropy(p, q) − the entropy of p): exact, ≥ 0, 0 iff the posteriors agree, +inf where q rules out
  a path p allows, 0 where p allows no path (a sum over no paths). Differentiable w.r.t. both.

  Args:
    p, q: LatticeInputs with the same shapes and length (checked when concrete).
  Returns:
    [] KL divergence.
  Example:
    >>> kl_divergence(LatticeInputs(*inputs, 5), LatticeInputs(*other_inputs, 5))
  """
  p, q = _same_lattice(p, q)
  post_p = forward_backward(*p)
  return _cross_entropy(post_p, q) - _entropy(post_p, *p[:4])  # both 0 where p allows no path


def _cross_entropy(post_p, q: LatticeInputs):
  """log P_q(ξ) − E_p[log P_q(ζ, ξ)]; +inf when some path p allows has zero probability under q (then the
  expectation is −inf, and so is log P_q(ξ) if q allows no path at all)."""
  expected = _expected_log_joint(post_p, *q[:4])
  value = jnp.where(jnp.isneginf(expected), jnp.inf, forward_backward(*q).log_likelihood - expected)
  return jnp.where(jnp.isfinite(post_p.log_likelihood), value, 0.0)


def _same_lattice(p: LatticeInputs, q: LatticeInputs):
  """Checks shapes and (concrete) lengths; returns both with the same explicit length."""
  p, q = as_inputs("p", p, LatticeInputs), as_inputs("q", q, LatticeInputs)
  for name, x in (("p", p), ("q", q)):
    try:
      check_inputs(*x)
    except ValueError as error:
      raise ValueError(f"{name}: {error}") from None
  for name, a, b in zip(LatticeInputs._fields[:4], p[:4], q[:4]):
    if jnp.shape(a) != jnp.shape(b):
      raise ValueError(f"p.{name} and q.{name} must have the same shape; got {jnp.shape(a)} and {jnp.shape(b)}")
  num_steps = jnp.shape(p.log_op)[0]
  lengths = [num_steps if x.length is None else x.length for x in (p, q)]
  try:
    differ = int(lengths[0]) != int(lengths[1])
  except TypeError:  # traced lengths: the caller's responsibility
    differ = False
  if differ:
    raise ValueError(f"p and q must have the same length; got {lengths[0]} and {lengths[1]}")
  return tuple(LatticeInputs(*in_common_dtype(*x[:4]), lengths[0]) for x in (p, q))


@accepts_inputs
def differentiable_sample(key, log_root, log_op, log_stop, log_cont, length=None, temperature=1.0,
                          method="straight-through"):
  """A posterior sample as frame indicators z [T, K, C] that gradients flow through.

  method="straight-through": z is one exact draw from P(ζ | ξ)^(1/temperature) (sample_posterior's), with
    z[t, h_t, τ_t] = 1 and zeros elsewhere and on padding; its gradient is that of its expectation E[z] = v
    (the tempered posterior's marginals): z = v + stop_gradient(one-hot − v). So the gradient of any linear
    function of z is exactly that of its expectation, and jax.grad of f(z) is ∂f/∂z · ∂v/∂inputs.
  method="perturb-and-marginals": the relaxed perturb-and-MAP sample (a stochastic softmax trick): Gumbel
    noise on every cell of log_op (each path visits one cell per step, so its score gains the sum of its
    cells' noise), then the marginals v of the perturbed lattice with all inputs divided by temperature.
    Smooth in the inputs; as temperature → 0 it becomes the one-hot of the perturbed lattice's Viterbi path
    (perturb-and-MAP), an approximate, not exact, posterior sample.

  Args:
    key: a PRNG key. temperature: [] a finite number > 0. method: "straight-through" or "perturb-and-marginals".
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length []: as forward_backward (or one
      LatticeInputs for the five).
  Returns:
    [T, K, C] z (each valid step sums to 1; zero on padding, and everywhere if no path explains the actions).
  Example:
    >>> z = differentiable_sample(jax.random.key(0), log_root, log_op, log_stop, log_cont, 5)
    >>> jax.grad(lambda op: jnp.sum(weights * differentiable_sample(key, log_root, op, log_stop, log_cont, 5)))(log_op)
  """
  check_key(key)
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  check_temperature(temperature)
  inputs = in_common_dtype(log_root, log_op, log_stop, log_cont)
  if method == "straight-through":
    path = sample_posterior(key, *inputs, length, temperature)
    v = forward_backward(*(x / temperature for x in inputs), length).v
    return v + jax.lax.stop_gradient(frame_indicators(path, v.shape) - v)
  if method == "perturb-and-marginals":
    perturbed = perturb(key, *inputs)
    return forward_backward(*(x / temperature for x in perturbed), length).v
  raise ValueError(f"method must be 'straight-through' or 'perturb-and-marginals'; got {method!r}")


def perturb(key, log_root, log_op, log_stop, log_cont):
  """The lattice with standard Gumbel noise added to every cell of log_op (−inf cells stay −inf): viterbi of
  the result is a perturb-and-MAP sample.

  Args:
    key: a PRNG key. log_root: [T, K]. log_op, log_stop, log_cont: [T, K, C].
  Returns:
    (log_root, log_op + noise, log_stop, log_cont).
  """
  noise = jax.random.gumbel(key, jnp.shape(log_op), jnp.result_type(log_op))
  return log_root, log_op + noise, log_stop, log_cont


def frame_indicators(path: LatticePath, shape):
  """[T, K, C] with 1 at each step's (h_t, τ_t) of `path` (procedures, counters [T]) and zeros elsewhere and on
  padding; shape: (T, K, C)."""
  num_steps, num_procs, capacity = shape
  valid = path.procedures != NO_FRAME
  cells = jnp.where(valid, path.procedures * capacity + path.counters, 0)
  return (jax.nn.one_hot(cells, num_procs * capacity) * valid[:, None]).reshape(shape)


class LatticeFilter(NamedTuple):
  """Result of `forward_filter`.

  Attributes:
    log_likelihood: [] log P(ξ), as forward_backward's.
    log_prefix: [T] log P(a_{0:t}): the total probability of every path prefix (h_0, τ_0) .. (h_t, τ_t)
      emitting a_0 .. a_t, before step t's termination (drawn on o_{t+1}) is decided; zero on padding.
    filtered: [T, K, C] P(h_t = h, τ_t = τ | a_{0:t}), the filter over frames given the prefix; zero on padding
      and where no prefix is possible.
  """
  log_likelihood: jax.Array
  log_prefix: jax.Array
  filtered: jax.Array


@accepts_inputs
def forward_filter(log_root, log_op, log_stop, log_cont, length=None) -> LatticeFilter:
  """The online forward pass: per step, the likelihood of the prefix and the filter over frames.

  "The last step must stop" concerns only the whole demonstration: log_prefix[t] does not include step t's
  termination factor, so it is the likelihood of a_{0:t} whether the path then stops or continues
  (for normalised ψ, and C large enough that no prefix is forced to stop, exactly log P(a_{0:t} | o_{0:t})).
  The whole demonstration's log P(ξ) = log_prefix[L−1] + log Σ_{h,τ} filtered[L−1]·exp(log_stop[L−1]).
  Differentiable by autodiff.

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length []: as forward_backward (or one LatticeInputs).
  Returns:
    LatticeFilter(log_likelihood [], log_prefix [T], filtered [T, K, C]).
  Example:
    >>> filt = forward_filter(log_root, log_op, log_stop, log_cont, length=5)
    >>> filt.filtered[2]  # [K, C] P(h_2, τ_2 | a_0, a_1, a_2)
  """
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  return _forward_filter_public(*in_common_dtype(log_root, log_op, log_stop, log_cont), length)


@jax.jit
def _forward_filter_public(log_root, log_op, log_stop, log_cont, length):
  num_steps, num_procs, capacity = log_op.shape
  is_push = _is_push(num_procs, capacity)
  can_continue = jnp.arange(num_procs * capacity) % capacity < capacity - 1
  op, stop, cont = (x.reshape(num_steps, -1) for x in (log_op, log_stop, log_cont))

  def step(carry, t):
    # continuing [S], pending []: log-mass entering step t relative to offset [], the running log-scale, summed
    # with Kahan's compensation (lost [], the low-order part the float additions dropped): float32 on long traces.
    continuing, pending, offset, lost = carry
    pushed = jnp.repeat(log_root[t] + pending, capacity)
    alpha = jnp.where(is_push, pushed, continuing) + op[t]
    log_mass = logsumexp(alpha)
    used = t < length
    filtered = jnp.where(used & jnp.isfinite(log_mass), jnp.exp(alpha - _finite_or_zero(log_mass)), 0.0)
    stop_total = logsumexp(alpha + stop[t])
    cont_scores = jnp.where(can_continue, alpha + cont[t], -jnp.inf)
    scale = _finite_or_zero(jnp.maximum(jnp.max(cont_scores), stop_total))
    added = scale - lost
    total = offset + added
    carry = (_shift(cont_scores, 1, -jnp.inf) - scale, stop_total - scale, total, (total - offset) - added)
    here = offset - lost
    return carry, (jnp.where(used, here + log_mass, 0.0), filtered, here + stop_total)

  init = (jnp.full(num_procs * capacity, -jnp.inf, log_op.dtype), jnp.zeros((), log_op.dtype),
          jnp.zeros((), log_op.dtype), jnp.zeros((), log_op.dtype))
  _, (log_prefix, filtered, log_final) = jax.lax.scan(step, init, jnp.arange(num_steps))
  return LatticeFilter(log_final[length - 1], log_prefix, filtered.reshape(log_op.shape))


class TwoLevelLattice(LatticeStructure):
  """The two-level lattice of one demonstration as a structure with queries (SynJax's distribution API; the
  same methods as php_jax.StackLattice): the posterior over latent paths P(ζ | ξ), restricted to the paths
  that agree with the annotation. A frozen pytree: pass it through jit and vmap.

  Args:
    inputs: LatticeInputs (log_root [T, K], log_op, log_stop, log_cont [T, K, C], length []).
    procedures, counters: [T] int annotation, −1 = unknown, or None (as forward_backward's).
  Raises:
    ValueError on construction, naming the argument (php_jax.inference.lattice's module docstring says what is checked).
  Example:
    >>> lattice = TwoLevelLattice(LatticeInputs(log_root, log_op, log_stop, log_cont, 5))
    >>> lattice.log_partition(), lattice.top_k(3).log_prob, lattice.kl_divergence(other)
  """

  def _checked(self):
    inputs = as_inputs("inputs", self.inputs, LatticeInputs)
    num_steps, num_procs, capacity, length = check_inputs(*inputs)
    inputs = LatticeInputs(*(x if hasattr(x, "dtype") else jnp.asarray(x) for x in inputs[:4]), inputs.length)
    procedures, counters = (None if x is None else check_annotation(name, x, (num_steps,), [(letter, size)], length)
                            for name, x, letter, size in (("procedures", self.procedures, "K", num_procs),
                                                          ("counters", self.counters, "C", capacity)))
    return inputs, procedures, counters

  def _annotated_inputs(self) -> LatticeInputs:
    """inputs with log_op restricted to the annotation."""
    return self.inputs._replace(log_op=annotated_log_op(self.inputs.log_op, self.procedures, self.counters,
                                                  check_inputs(*self.inputs)[3]))

  def log_partition(self) -> jax.Array:
    """[] log P(ξ) (of the agreeing paths)."""
    return self.posterior().log_likelihood

  def posterior(self) -> LatticePosterior:
    """forward_backward: LatticePosterior(log_likelihood [], v = marginals [T, K, C], w [T, K, C])."""
    return forward_backward(self.inputs, procedures=self.procedures, counters=self.counters)

  def marginals(self) -> jax.Array:
    """[T, K, C] P(h_t = h, τ_t = τ | ξ)."""
    return self.posterior().v

  def argmax(self) -> LatticePath:
    """The most likely path (viterbi): procedures, counters [T], log_prob []."""
    return viterbi(self.inputs, procedures=self.procedures, counters=self.counters)

  def top_k(self, k: int) -> LatticePath:
    """The k most likely paths, best first: procedures, counters [k, T], log_prob [k]."""
    return top_k(k, self.inputs, procedures=self.procedures, counters=self.counters)

  def sample(self, key, temperature=1.0) -> LatticePath:
    """One exact draw from P(ζ | ξ)^(1/temperature), renormalised; log_prob [] untempered log P(ζ, ξ)."""
    return sample_posterior(key, self.inputs, temperature=temperature, procedures=self.procedures,
                            counters=self.counters)

  def entropy(self) -> jax.Array:
    """[] H(P(ζ | ξ)) in nats."""
    return posterior_entropy(self.inputs, procedures=self.procedures, counters=self.counters)

  def cross_entropy(self, other: TwoLevelLattice) -> jax.Array:
    """[] H(self, other) in nats between the posteriors over paths (same shapes and length); +inf where
    other rules out a path self allows."""
    return cross_entropy(self._annotated_inputs(), self._same_kind(other)._annotated_inputs())

  def kl_divergence(self, other: TwoLevelLattice) -> jax.Array:
    """[] KL(self ‖ other) in nats between the posteriors over paths (same shapes and length)."""
    return kl_divergence(self._annotated_inputs(), self._same_kind(other)._annotated_inputs())
