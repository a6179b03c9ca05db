"""The E-step: exact inference on the padded (procedure h, counter τ) lattice of a two-level PHP.

One demonstration of T steps, K procedures, counter capacity C. Inputs are log-probabilities:

  log_root  [T, K]     log η_⊥(h | o_t): the root pushes h at step t (t = 0, or after a stop at t-1).
  log_op    [T, K, C]  log η_h^τ(a_t | o_t) of the demonstrated action.
  log_stop  [T, K, C]  log ψ_h^τ(1 | o_{t+1}).
  log_cont  [T, K, C]  log ψ_h^τ(0 | o_{t+1}).
  length    []  int    steps used (1 ≤ length ≤ T); steps t ≥ length are padding.

A path starts in (h_0, 0); the frame (h_t, τ_t) emits a_t; then it stops (the root pushes (h', 0)) or
continues to (h_t, τ_t + 1), impossible at τ_t + 1 = C; the last step must stop.

The lattice is a semi-Markov chain with one structural fact that makes inference cheap: (h, τ+1) at t+1 has
the single predecessor (h, τ) at t. Hence w_t = shift(v_{t+1}), and

  v_t = w_t + s_t · q_t,   s_t = Σ_h v_{t+1}(h, 0),   q_t ∝ α_t · η_t · ψ_t(1)  (the filter given a stop at t),

so after a log-space forward filter (one exp per cell) the smoother runs in probability space with no
transcendental functions, Viterbi needs one backpointer per step, and posterior sampling is exact
forward-filter backward-sample. The forward carry is renormalised every step, so float32 stays accurate on
traces of 10,000 steps with large logits; −inf masks give exact zeros, never NaN.

One dialect for both lattices (this one and php_jax.inference.stack_lattice's whole call stack): every E-step function
takes its lattice as one inputs object, LatticeInputs here (f(inputs, ...) is f(log_root, log_op, log_stop,
log_cont, length, ...): the arguments after it fill the function's other parameters in order), and an
annotation as `procedures`, `counters` (int, −1 = unknown; [T] here, [T, d] for the stack; pass them by
keyword); results name the frame marginals `marginals` (here the posterior's field `v`, the paper's name, which
`marginals` reads), a path's frames `procedures`, `counters` and its log P(ζ, ξ) `log_prob`.
`php_jax.TwoLevelLattice(inputs, procedures, counters)` (php_jax.inference.lattice_ops) answers the same queries
as `php_jax.StackLattice`.

Refused, with a ValueError naming the argument: an input that is not a float array (None, integer and
boolean arrays; nested lists of floats are taken), shapes that do not match, a length that is not an integer
in 1..T, a temperature that is not a finite number > 0, a key that is not one PRNG key, an annotation that is
not an integer array of the right shape and, when concrete, NaN or +inf in an input or an annotation value
outside −1..K−1 / −1..C−1 on a step before length. Under jit or vmap only shapes and dtypes are checked: a
traced length outside 1..T or a traced temperature ≤ 0 gives a meaningless result, NaN or +inf gives NaN,
and a traced annotation value out of range matches nothing (validate_inputs checks a lattice's values before
you jit). Arrays of different float dtypes are not refused (Dtypes).

Dtypes: float32 and float64 inputs are computed in their own dtype, arrays of different dtypes in the
promoted one. float16 and bfloat16 inputs are computed in float32 and the results are float32 (a long
trace's log-likelihood is beyond float16's range, −65,504, and the recursions' sums need more than its 3
significant digits); gradients with respect to the inputs come back in the inputs' dtype.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp

from php_jax.inference.lattice_inputs import (NO_FRAME, LatticeInputs, LatticePath, LatticePosterior,
                                              LatticeStructure, accepts_inputs, annotate, annotated_log_op,
                                              check_annotation, check_inputs, check_key, check_length,
                                              check_log_probs, check_temperature, described, in_common_dtype,
                                              no_frame_unless_explained, validate_inputs)

__all__ = ["NO_FRAME", "LatticeInputs", "LatticePath", "LatticePosterior", "LatticeStructure", "accepts_inputs",
           "annotate", "complete_log_likelihood", "forward_backward", "max_marginal_path", "posterior_entropy",
           "sample_posterior", "top_level", "validate_inputs", "viterbi"]


def _finite_or_zero(x):
  return jnp.where(jnp.isfinite(x), x, 0.0)


def _shift(x, by: int, fill):
  """Shifts the last axis by ±1 (out[s] = x[s - by]), filling the vacated end. Unlike jnp.roll this is
  one cheap concatenate on the CPU, which matters inside scan bodies."""
  pad = jnp.full(x.shape[:-1] + (1,), fill, x.dtype)
  return jnp.concatenate([pad, x[..., :-1]] if by == 1 else [x[..., 1:], pad], axis=-1)


def _is_push(num_procs, capacity):
  """[S] bool: cells with τ = 0, with (h, τ) flattened to s = h·C + τ."""
  return jnp.arange(num_procs * capacity) % capacity == 0


def _forward_scan(log_root, log_op, log_stop, log_cont, length, semiring_max: bool):
  """α recursion over flattened cells, renormalised every step.

  The carry is (continuing cells' log-mass [S], pending log stop mass []), both relative to the running
  scale; step t pushes with log η_⊥(· | o_t) itself. The stop and continue scores of the emission are
  summed once outside the scan and read by index (scanning over them as xs would make vmap transpose
  them time-major first, a full copy each). The carry runs on through padding.

  Returns:
    log_increments: [T] summing to log P(ξ) (max-product: the best path's log-probability).
    stops: [T, S] sum-product: the stop filter q_t = P(h_t, τ_t | o_{0:t+1}, a_{0:t}, stop at t) over
      flat cells, the final-state posterior at t = length-1, zero on padding and where no stop is
      possible. [T] max-product: the best stopping cell.
  """
  num_steps, num_procs, capacity = log_op.shape
  is_push = _is_push(num_procs, capacity)
  can_continue = jnp.arange(num_procs * capacity) % capacity < capacity - 1
  op_stop = (log_op + log_stop).reshape(num_steps, -1)
  op_cont = jnp.where(can_continue, (log_op + log_cont).reshape(num_steps, -1), -jnp.inf)

  def step(carry, t):
    continuing, pending = carry
    pushed = jnp.broadcast_to((log_root[t] + pending)[:, None], (num_procs, capacity)).reshape(-1)
    alpha = jnp.where(is_push, pushed, continuing)
    stop_scores = alpha + op_stop[t]
    cont_scores = alpha + op_cont[t]
    if semiring_max:
      stops = jnp.argmax(stop_scores).astype(jnp.int32)
      stop_total = stop_scores[stops]
    else:
      peak = _finite_or_zero(jnp.max(stop_scores))
      weights = jnp.exp(stop_scores - peak)
      total = jnp.sum(weights)
      empty = total == 0  # a log guarded so that no derivative divides by a zero total (0/0: NaN); a NaN passes
      stop_total = jnp.where(empty, -jnp.inf, jnp.log(jnp.where(empty, 1.0, total)) + peak)
      used = (t < length) & (total > 0)  # dividing keeps the smoother's mass exactly 1
      stops = jnp.where(used, weights / jnp.where(used, total, 1.0), 0.0)
    scale = _finite_or_zero(jnp.maximum(jnp.max(cont_scores), stop_total))
    carry = (_shift(cont_scores, 1, -jnp.inf) - scale, stop_total - scale)
    increment = jnp.where(t == length - 1, stop_total, jnp.where(t < length - 1, scale, 0.0))
    return carry, (increment, stops)

  init = (jnp.full(num_procs * capacity, -jnp.inf, log_op.dtype), jnp.zeros((), log_op.dtype))
  _, (log_increments, stops) = jax.lax.scan(step, init, jnp.arange(num_steps))
  return log_increments, stops


def _forward_filter(log_root, log_op, log_stop, log_cont, length):
  """Sum-product forward pass: (log_likelihood [], stop filter q [T, S], as in _forward_scan)."""
  log_increments, stop_filter = _forward_scan(log_root, log_op, log_stop, log_cont, length, semiring_max=False)
  return jnp.sum(log_increments), stop_filter


def _backward_smoother(stop_filter, length, capacity):
  """v, w [T, S] from the stop filter: v_{L-1} = q_{L-1}, v_t = shift(v_{t+1}) + s_t q_t, w_t = shift(v_{t+1}).

  Padding needs no masks: q and v are zero there, so zeros propagate.
  """
  num_cells = stop_filter.shape[1]
  is_push = _is_push(num_cells // capacity, capacity)
  is_last = jnp.roll(is_push, -1)

  def shift_down(v):  # out[h, τ] = v[h, τ+1], zero at τ = C-1
    return jnp.where(is_last, 0.0, _shift(v, -1, 0.0))

  def step(v_next, t):
    pushed_next = jnp.where(t == length - 1, 1.0, jnp.sum(v_next[::capacity]))  # Σ_h v_{t+1}(h, 0)
    v = shift_down(v_next) + pushed_next * stop_filter[t]
    return v, v

  _, v = jax.lax.scan(step, jnp.zeros_like(stop_filter[0]), jnp.arange(stop_filter.shape[0]), reverse=True)
  w = shift_down(jnp.concatenate([v[1:], jnp.zeros_like(v[:1])]))
  return v, w


def _posterior_impl(log_root, log_op, log_stop, log_cont, length):
  log_likelihood, stop_filter = _forward_filter(log_root, log_op, log_stop, log_cont, length)
  v, w = _backward_smoother(stop_filter, length, log_op.shape[2])
  return log_likelihood, v.reshape(log_op.shape), w.reshape(log_op.shape)


@jax.custom_jvp
def _posterior(log_root, log_op, log_stop, log_cont, length):
  return _posterior_impl(log_root, log_op, log_stop, log_cont, length)


@_posterior.defjvp
def _posterior_jvp(primals, tangents):
  """d log P = Σ v·d log_op + w·d log_cont + (v − w)·d log_stop + v[:, :, 0]·d log_root (the EG identities):
  linear in the tangents with the marginals as coefficients, so reverse mode transposes it to g·v, ... at no
  extra cost. The tangents of v and w come from forward-mode autodiff of the implementation."""
  inputs, length = tuple(primals[:4]), primals[4]
  d_root, d_op, d_stop, d_cont = tangents[:4]
  (log_likelihood, v, w), (_, d_v, d_w) = jax.jvp(lambda *a: _posterior_impl(*a, length), inputs,
                                                  tuple(tangents[:4]))
  d_log_likelihood = (jnp.sum(v[:, :, 0] * d_root) + jnp.sum(v * d_op) + jnp.sum((v - w) * d_stop)
                      + jnp.sum(w * d_cont))
  return (log_likelihood, v, w), (d_log_likelihood, d_v, d_w)


_posterior_jit = jax.jit(_posterior)


@accepts_inputs
def forward_backward(log_root, log_op, log_stop, log_cont, length=None, procedures=None,
                     counters=None) -> LatticePosterior:
  """Exact log-likelihood and single-step posterior marginals of one demonstration.

  Gradients: ∂ log_likelihood / ∂ log_op = v, / ∂ log_cont = w, / ∂ log_stop = v − w,
  / ∂ log_root[t, h] = v[t, h, 0]. A custom JVP rule returns the tangent of log_likelihood as the marginals
  times the input tangents, which reverse mode transposes at no extra cost, so `jax.grad` of `log_likelihood`
  is the paper's Expectation–Gradient gradient for the price of the forward–backward. Forward mode
  (`jax.jvp`, `jax.jacfwd`, `jax.hessian`) works too; tangents of v and w come from autodiff of the
  recursions. Memory is linear in T. Batch with `jax.vmap`.

  Args:
    log_root: [T, K] log η_⊥(h | o_t). Or one LatticeInputs in its place, for the first five arguments.
    log_op: [T, K, C] log η_h^τ(a_t | o_t).
    log_stop: [T, K, C] log ψ_h^τ(1 | o_{t+1}).
    log_cont: [T, K, C] log ψ_h^τ(0 | o_{t+1}).
    length: [] int in 1..T, default T. Under jit or vmap a length outside 1..T is not refused (the result
      is then meaningless): call validate_inputs first, or use jax.experimental.checkify.
    procedures, counters: [T] int annotation, the known h_t in 0..K−1 and τ_t in 0..C−1, −1 = unknown (either
      may be None): only the paths that agree count, so a full annotation gives the complete-data
      log-likelihood. The same as passing annotate(log_op, procedures, counters); padding is ignored.
    float16 / bfloat16 inputs are computed in float32 (results float32, gradients in the inputs' dtype).

  Returns:
    LatticePosterior(log_likelihood [], v [T, K, C], w [T, K, C]).

  Example:
    >>> post = forward_backward(log_root, log_op, log_stop, log_cont, length=5)
    >>> loss = -post.log_likelihood  # jax.grad(loss) flows into the networks that made the inputs
    >>> forward_backward(LatticeInputs(log_root, log_op, log_stop, log_cont, 5), procedures=known_h)
  """
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = annotated_log_op(log_op, procedures, counters, length)
  return LatticePosterior(*_posterior_jit(*in_common_dtype(log_root, log_op, log_stop, log_cont), length))


@accepts_inputs
def viterbi(log_root, log_op, log_stop, log_cont, length=None, procedures=None, counters=None) -> LatticePath:
  """Most likely latent path (max-product forward, one backpointer per step).

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the first five).
  Returns:
    LatticePath(procedures [T], counters [T], log_prob []); where no path explains the actions, log_prob −inf
    and NO_FRAME at every step (as top_k).
  """
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = annotated_log_op(log_op, procedures, counters, length)
  return _viterbi(*in_common_dtype(log_root, log_op, log_stop, log_cont), length)


@jax.jit
def _viterbi(log_root, log_op, log_stop, log_cont, length):
  num_steps, _, capacity = log_op.shape
  log_increments, best_stop = _forward_scan(log_root, log_op, log_stop, log_cont, length, semiring_max=True)

  def backtrack(state_next, xs):
    t, best = xs
    tau_next = state_next % capacity
    state = jnp.where(t == length - 1, best, jnp.where(tau_next > 0, state_next - 1, best))
    state = jnp.where(t < length, state, NO_FRAME)
    return jnp.where(t < length, state, state_next), state

  _, states = jax.lax.scan(backtrack, jnp.int32(0), (jnp.arange(num_steps), best_stop), reverse=True)
  log_prob = jnp.sum(log_increments)
  return _path_from_states(*no_frame_unless_explained(log_prob, states), capacity, log_prob)


@accepts_inputs
def sample_posterior(key, log_root, log_op, log_stop, log_cont, length=None, temperature=1.0, procedures=None,
                     counters=None) -> LatticePath:
  """One exact sample from P(ζ | ξ)^(1/temperature), renormalised (forward filter, backward sample).

  A path's log P(ζ, ξ) is a sum of one log_root / log_op / log_stop / log_cont term per step, so the tempered
  posterior is the posterior of the lattice with all four inputs divided by temperature (> 0): 1 is the
  posterior itself, → 0 approaches the Viterbi path, → ∞ the uniform distribution over possible paths.
  Vmap over keys for many samples.

  Args:
    key: a PRNG key. temperature: [] a finite number > 0.
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the five; pass temperature and the annotation by keyword).
  Returns:
    LatticePath(procedures [T], counters [T], log_prob []): log_prob is log P(ζ, ξ) under the untempered model;
    where no path explains the actions, −inf and NO_FRAME at every step.
  Example:
    >>> path = sample_posterior(jax.random.key(0), log_root, log_op, log_stop, log_cont, 5, temperature=0.5)
  """
  check_key(key)
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  check_temperature(temperature)
  log_op = annotated_log_op(log_op, procedures, counters, length)
  return _sample_posterior(key, *in_common_dtype(log_root, log_op, log_stop, log_cont), length, temperature)


@jax.jit
def _sample_posterior(key, log_root, log_op, log_stop, log_cont, length, temperature):
  num_steps, _, capacity = log_op.shape
  tempered = (x / temperature for x in (log_root, log_op, log_stop, log_cont))
  log_likelihood, stop_filter = _forward_filter(*tempered, length)

  def backward(state_next, xs):
    t, step_key, q = xs
    drawn = jax.random.categorical(step_key, jnp.log(q)).astype(jnp.int32)
    tau_next = state_next % capacity
    state = jnp.where(t == length - 1, drawn, jnp.where(tau_next > 0, state_next - 1, drawn))
    state = jnp.where(t < length, state, NO_FRAME)
    return jnp.where(t < length, state, state_next), state

  keys = jax.random.split(key, num_steps)
  _, states = jax.lax.scan(backward, jnp.int32(0), (jnp.arange(num_steps), keys, stop_filter),
                           reverse=True)
  path = _path_from_states(*no_frame_unless_explained(log_likelihood, states), capacity, jnp.zeros(()))
  return path._replace(log_prob=_complete_log_likelihood(
      log_root, log_op, log_stop, log_cont, path.procedures, path.counters, length))


def max_marginal_path(posterior: LatticePosterior, length=None) -> LatticePath:
  """Per step the most probable (h, τ) under v. Not always a valid path; log_prob is not computed (NaN).

  Args:
    posterior: forward_backward's result (v [T, K, C]). length: [] int in 1..T, default T (as
      forward_backward's: a traced one is not range-checked).
  Returns:
    LatticePath(procedures [T], counters [T], log_prob [] NaN).
  """
  if not isinstance(posterior, LatticePosterior):
    raise ValueError(f"posterior must be a LatticePosterior (forward_backward's result); got {described(posterior)}")
  num_steps, _, capacity = posterior.v.shape
  length = check_length(length, num_steps)
  states = jnp.argmax(posterior.v.reshape(num_steps, -1), axis=1).astype(jnp.int32)
  states = jnp.where(jnp.arange(num_steps) < length, states, NO_FRAME)
  return _path_from_states(states, capacity, jnp.full((), jnp.nan, posterior.v.dtype))


def _path_from_states(states, capacity, log_prob):
  padding = states == NO_FRAME
  proc, tau = jnp.divmod(jnp.where(padding, 0, states), capacity)
  return LatticePath(jnp.where(padding, NO_FRAME, proc).astype(jnp.int32),
                     jnp.where(padding, NO_FRAME, tau).astype(jnp.int32), log_prob)


@accepts_inputs
def complete_log_likelihood(log_root, log_op, log_stop, log_cont, procedure, counter, length=None):
  """log P(ζ, ξ) of an annotated path, computed directly (−inf if the path breaks the semantics).

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length []: as forward_backward (or one
      LatticeInputs: complete_log_likelihood(inputs, procedure, counter)).
    procedure, counter: [T] int, the frame (h_t, τ_t) of each step, in 0..K−1 and 0..C−1 (−1, no frame, gives
      −inf); values on padding are ignored.
  Returns:
    [] the complete-data log-likelihood.
  """
  num_steps, num_procs, capacity, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  procedure = check_annotation("procedure", procedure, (num_steps,), [("K", num_procs)], length)
  counter = check_annotation("counter", counter, (num_steps,), [("C", capacity)], length)
  return _complete_log_likelihood(*in_common_dtype(log_root, log_op, log_stop, log_cont), procedure, counter, length)


@jax.jit
def _complete_log_likelihood(log_root, log_op, log_stop, log_cont, procedure, counter, length):
  num_steps, num_procs, capacity = log_op.shape
  t = jnp.arange(num_steps)
  valid = t < length
  proc = jnp.clip(procedure, 0, num_procs - 1)
  tau = jnp.clip(counter, 0, capacity - 1)
  in_range = (procedure == proc) & (counter == tau)
  next_proc, next_tau = jnp.roll(procedure, -1), jnp.roll(counter, -1)
  continues = (next_tau == counter + 1) & (next_proc == procedure)
  pushes = next_tau == 0
  last = t == length - 1
  transition = jnp.where(
      last | pushes,
      log_stop[t, proc, tau] + jnp.where(last, 0.0, jnp.roll(log_root, -1, axis=0)[t, jnp.roll(proc, -1)]),
      jnp.where(continues, log_cont[t, proc, tau], -jnp.inf))
  starts_at_zero = counter[0] == 0
  terms = jnp.where(in_range, log_op[t, proc, tau] + transition, -jnp.inf)
  total = log_root[0, proc[0]] + jnp.sum(jnp.where(valid, terms, 0.0))
  return jnp.where(starts_at_zero, total, -jnp.inf)


def top_level(log_stop, length=None):
  """The top level's lattice (K = 1, called once): no stop before the last step.

  Args:
    log_stop: [T, 1, C]. length: [] int in 1..T, default T (as forward_backward's: a traced one is not
      range-checked).
  Returns:
    [T, 1, C] log_stop with −inf before step length − 1.
  """
  log_stop = check_log_probs("log_stop", log_stop, "[T, 1, C]")
  if jnp.ndim(log_stop) != 3 or jnp.shape(log_stop)[1] != 1:
    raise ValueError(f"log_stop must be [T, 1, C] (the top level has one procedure); got shape {jnp.shape(log_stop)}")
  num_steps = log_stop.shape[0]
  length = check_length(length, num_steps)
  early = jnp.arange(num_steps) < length - 1
  return jnp.where(early[:, None, None], -jnp.inf, log_stop)


@accepts_inputs
def posterior_entropy(log_root, log_op, log_stop, log_cont, length=None, procedures=None, counters=None):
  """Entropy of P(ζ | ξ) in nats: log P(ξ) − E[log P(ζ, ξ)], from the marginals; 0 where no path explains
  ξ (a sum over no paths).

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the first five).
  Returns:
    [] nats.
  """
  _, _, _, checked_length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = annotated_log_op(log_op, procedures, counters, checked_length)
  inputs = in_common_dtype(log_root, log_op, log_stop, log_cont)
  return _entropy(forward_backward(*inputs, length), *inputs)


def _entropy(posterior: LatticePosterior, log_root, log_op, log_stop, log_cont):
  """log P(ξ) − E[log P(ζ, ξ)] from `posterior` of the lattice (log_root, ...); 0 where no path explains ξ (a sum
  over no paths), its gradient finite there too. Returns []."""
  explained = jnp.isfinite(posterior.log_likelihood)
  joint = _expected_log_joint(posterior, log_root, log_op, log_stop, log_cont)
  return jnp.where(explained, jnp.where(explained, posterior.log_likelihood, 0.0) - joint, 0.0)


def _expected_log_joint(posterior: LatticePosterior, log_root, log_op, log_stop, log_cont):
  """E[log P'(ζ, ξ)] over paths drawn from `posterior`'s marginals, for the lattice (log_root, ...) of the
  same shape: one term per step, so Σ v·log_op + w·log_cont + (v − w)·log_stop + v[:, :, 0]·log_root.
  Cells of zero probability count 0 even where the log-factor is −inf, in values and in gradients. Returns []."""
  v, w = posterior.v, posterior.w

  def expected(prob, log_factor):
    used = prob > 0
    return jnp.sum(jnp.where(used, prob * jnp.where(used, log_factor, 0.0), 0.0))

  return (expected(v[:, :, 0], log_root) + expected(v, log_op) + expected(w, log_cont)
          + expected(v - w, log_stop))
