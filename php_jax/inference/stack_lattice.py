"""Exact inference over the whole call stack of a d-level PHP (the "exponential" E-step of paper §4.2.3).

Levels 0 (the root, K_0 = 1) .. d-1 (the lowest, emits elementary actions); level i has K_i procedures and
counter capacity C_i. At every elementary step the stack holds one frame (h_i, τ_i) per level, so the latent
state is the tensor index s = (h_0, τ_0, h_1, τ_1, ..., h_{d-1}, τ_{d-1}) of shape [1, C_0, K_1, C_1, ...]
(S = Π K_i C_i states; the root's K_0 = 1 axis costs nothing). One demonstration of T padded steps:

  log_call[i]  [T, K_i, C_i, K_{i+1}]  log η_{i,h}^τ(h' | o_t): frame (h, τ) of level i < d-1 calls h' at step t.
  log_act      [T, K_{d-1}, C_{d-1}]   log η_{d-1,h}^τ(a_t | o_t) of the demonstrated action.
  log_stop[i]  [T, K_i, C_i]           log ψ_{i,h}^τ(1 | o_{t+1}); log_cont[i] the same for 0 (continue).
  length       []  int                 steps used (1..T); steps ≥ length are padding.

Semantics (the executor's): at t = 0 the root frame (0, 0) pushes a chain of frames (h_i, 0) down to level
d-1. The lowest frame emits a_t. Then, from the bottom up, each level stops or continues; the first level j
that continues moves to τ_j + 1 (impossible at C_j) and levels j+1..d-1 are pushed afresh at step t+1 with
τ = 0, each calling the next with `log_call[·][t+1]`. All d levels stop exactly after step length-1, never before.

The transition is never formed as an S × S matrix. It factors into a stop cascade and a push chain:

  cascade (step t)   m_{d-1} = α_t + log_act_t;  cont_i = m_i + log_cont_i;  m_{i-1} = ⊕_{h_i,τ_i} m_i + log_stop_i
  push (step t+1)    g_0 = [start | cont_0 shifted by one along τ_0];   α_{t+1} = g_{d-1};
                     g_{i+1} = [g_i + log_call_i (at τ_{i+1} = 0) | cont_{i+1} shifted by one along τ_{i+1}]

where m_i is over levels 0..i (the mass of every stack whose levels below i all stopped), ⊕ is logsumexp
(sum-product) or max (max-product), and m_{-1} is the mass of ending the episode, used at the last step only.
A state's deepest level with τ > 0 is the level that continued, so each state of step t+1 has exactly one
"shape" of predecessor: the same levels 0..j (τ_j one less) and any stopped frames below, chosen by the cascade.
Hence Viterbi needs one backpointer table per level and step (over levels above it: tiny), and exact posterior
sampling draws the stopped frames level by level from the cascade's stop scores (forward filter, backward sample).

Marginals come from automatic differentiation: per-level potentials u_i [T, K_i, C_i] (0, or −inf outside an
annotation) are added to the frames, and P(h_{i,t} = h, τ_{i,t} = τ | ξ) = ∂ log P(ξ) / ∂ u_i[t, h, τ], so one
reverse pass gives every level's marginals, and jax.grad of log P(ξ) with respect to the inputs is the
posterior of each event (the EG gradient). The carry is renormalised every step by its maximum (a constant to
autodiff, which keeps the gradient exact), so float32 stays finite on long traces with large logits, and
logsumexp is guarded so −inf masks give exact zeros and zero gradients, never NaN.

The same dialect as php_jax.inference.lattice: every function takes one StackInputs, an annotation as `procedures`,
`counters` [T, d] int (root first, −1 = unknown), and returns `log_likelihood`, `marginals`, and paths with
`procedures`, `counters`, `log_prob`; top_k, the entropy and KL divergence / cross-entropy come from the same
recursions (k-best lists per state; the event posteriors above times the log-factors). `StackLattice` is the
structure answering every query, like php_jax.TwoLevelLattice. Refused with a ValueError naming the argument,
as in php_jax.inference.lattice: inputs that are not a StackInputs (or a plain tuple of its fields), an input that is not
a float array (nested lists of floats are taken), shapes that do not match, a length that is not an integer in
1..T, a temperature that is not a finite number > 0, a key that is not one PRNG key, an annotation that is not
an integer array [T, d] and, when concrete, NaN or +inf in an input or an annotation value outside
−1..K_i−1 / −1..C_i−1 on a step before length. Under jit or vmap only the structure, shapes and dtypes are
checked (a traced length or temperature out of range gives a meaningless result, NaN or +inf gives NaN, and
a traced annotation value out of range matches nothing). Arrays of different dtypes are computed in the
promoted one; unlike the two-level lattice, float16 and bfloat16 inputs are computed in their own dtype.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from php_jax.inference.lattice_inputs import (
  LatticeStructure,
  as_inputs,
  check_annotation,
  check_finite,
  check_k,
  check_key,
  check_length,
  check_log_probs,
  check_temperature,
  described,
  no_frame_unless_explained,
)
from php_jax.inference.stack_recursions import (annotation_potentials, backtrack, entropy_and_events, evidence,
                                                expected_log_joint, forward, forward_top_k, logsumexp)


class StackInputs(NamedTuple):
  """One demonstration's stack lattice (module docstring). log_call has d-1 arrays, log_stop and log_cont d.

  Attributes:
    log_call: tuple of [T, K_i, C_i, K_{i+1}]. log_act: [T, K_{d-1}, C_{d-1}].
    log_stop, log_cont: tuples of [T, K_i, C_i]. length: [] int or None (= T).
  """
  log_call: tuple
  log_act: jax.Array
  log_stop: tuple
  log_cont: tuple
  length: Any = None


class StackPosterior(NamedTuple):
  """Result of `forward_backward`.

  Attributes:
    log_likelihood: [] log P(ξ) (restricted to the annotation, if any); −inf if no path is possible.
    marginals: tuple of d arrays [T, K_i, C_i], P(h_{i,t} = h, τ_{i,t} = τ | ξ); zero on padding.
  """
  log_likelihood: jax.Array
  marginals: tuple


class StackPath(NamedTuple):
  """One whole-stack latent path.

  Attributes:
    procedures: [T, d] int32 h_{i,t} (level 0's is 0), NO_FRAME on padding (and in every frame where no path
      explains the actions).
    counters: [T, d] int32 τ_{i,t}, NO_FRAME where procedures is.
    log_prob: [] log P(ζ, ξ) of the path (its complete-data log-likelihood).
  """
  procedures: jax.Array
  counters: jax.Array
  log_prob: jax.Array


def _check_inputs(inputs: StackInputs, name: str = "inputs"):
  """Validates the structure, dtypes and shapes (static), the length and, when concrete, the values on the
  steps before it (no NaN or +inf); returns (inputs as a StackInputs of arrays, the length as an int32 array)."""
  inputs = as_inputs(name, inputs, StackInputs)
  for field in ("log_call", "log_stop", "log_cont"):
    if not isinstance(getattr(inputs, field), (tuple, list)):
      raise ValueError(f"{field} must be a tuple of arrays, one per level (d−1 in log_call, d in log_stop and "
                       f"log_cont); got {described(getattr(inputs, field))}")
  log_call, log_act, log_stop, log_cont, length = inputs
  depth = len(log_stop)
  if depth < 2 or len(log_cont) != depth or len(log_call) != depth - 1:
    raise ValueError(f"need d ≥ 2 levels: d arrays in log_stop and log_cont, d-1 in log_call; got "
                     f"{len(log_call)}, {len(log_stop)}, {len(log_cont)}")
  log_call = tuple(check_log_probs(f"log_call[{i}]", x, "[T, K_i, C_i, K_{i+1}]") for i, x in enumerate(log_call))
  log_act = check_log_probs("log_act", log_act, "[T, K_{d-1}, C_{d-1}]")
  log_stop, log_cont = (tuple(check_log_probs(f"{field}[{i}]", x, "[T, K_i, C_i]") for i, x in enumerate(arrays))
                        for field, arrays in (("log_stop", log_stop), ("log_cont", log_cont)))
  for field, x in (("log_act", log_act), *((f"log_stop[{i}]", x) for i, x in enumerate(log_stop))):
    if jnp.ndim(x) != 3 or min(jnp.shape(x)) < 1:
      raise ValueError(f"{field} must be [T, K, C] with T, K, C ≥ 1; got shape {jnp.shape(x)}")
  num_steps = jnp.shape(log_act)[0]
  sizes = tuple(jnp.shape(x)[1] for x in log_stop)
  capacities = tuple(jnp.shape(x)[2] for x in log_stop)
  expected = {f"log_stop[{i}]": (log_stop[i], (num_steps, sizes[i], capacities[i])) for i in range(depth)}
  expected.update({f"log_cont[{i}]": (log_cont[i], (num_steps, sizes[i], capacities[i])) for i in range(depth)})
  expected.update({f"log_call[{i}]": (log_call[i], (num_steps, sizes[i], capacities[i], sizes[i + 1]))
                   for i in range(depth - 1)})
  expected["log_act"] = (log_act, (num_steps, sizes[-1], capacities[-1]))
  for field, (x, shape) in expected.items():
    if jnp.shape(x) != shape:
      raise ValueError(f"{field} must have shape {shape}; got {jnp.shape(x)}")
  if sizes[0] != 1:
    raise ValueError(f"the root level has one procedure: log_stop[0] must be [T, 1, C_0]; got {jnp.shape(log_stop[0])}")
  checked = check_length(length, num_steps)
  inputs = StackInputs(log_call, log_act, log_stop, log_cont, length)
  check_finite(dict(_named_arrays(inputs)), checked)
  return inputs, checked


def _check_annotation(inputs: StackInputs, procedures, counters, length):
  """The annotation checked (integer [T, d]; when concrete, values in range on the steps before length)."""
  num_steps, depth = jnp.shape(inputs.log_act)[0], len(inputs.log_stop)
  checked = []
  for name, values, axis, letter in (("procedures", procedures, 1, "K"), ("counters", counters, 2, "C")):
    bounds = [(f"{letter}_{i}", jnp.shape(x)[axis]) for i, x in enumerate(inputs.log_stop)]
    checked.append(None if values is None else check_annotation(name, values, (num_steps, depth), bounds, length))
  return checked


def _prepared(inputs: StackInputs, procedures=None, counters=None, fill_unknown=False, name="inputs"):
  """The public functions' checks (module docstring): (inputs with length None, every array in the promoted
  dtype; procedures; counters; length [] int32). fill_unknown: None annotations as −1 arrays."""
  inputs, length = _check_inputs(inputs, name)
  procedures, counters = _check_annotation(inputs, procedures, counters, length)
  if fill_unknown:
    procedures, counters = _unknown_as_arrays(inputs, procedures, counters)
  fields = tuple(inputs[:4])
  dtype = jnp.result_type(*jax.tree.leaves(fields))
  fields = jax.tree.map(lambda x: x if x.dtype == dtype else x.astype(dtype), fields)
  return StackInputs(*fields), procedures, counters, length


def _unknown_as_arrays(inputs: StackInputs, procedures, counters):
  """None annotations as −1 arrays [T, d] (all unknown), so that the free and the annotated lattice share one
  compiled program."""
  shape = (jnp.shape(inputs.log_act)[0], len(inputs.log_stop))
  return tuple(jnp.full(shape, -1, jnp.int32) if x is None else x for x in (procedures, counters))


@jax.jit
def _posterior(inputs: StackInputs, procedures, counters, length):
  potentials = annotation_potentials(inputs, procedures, counters)
  return jax.value_and_grad(evidence, argnums=1)(inputs, potentials, length)


@jax.jit
def _annotated_log_likelihood(inputs: StackInputs, procedures, counters, length):
  return evidence(inputs, annotation_potentials(inputs, procedures, counters), length)


def log_likelihood(inputs: StackInputs, procedures=None, counters=None, temperature=1.0) -> jax.Array:
  """forward_backward's log_likelihood [] alone (the forward pass only): for a loss, whose jax.grad gives the
  same posteriors, or for scoring. With a temperature T, the tempered T · log Σ_ζ P(ζ, ξ)^(1/T), whose jax.grad
  gives the posteriors of P(ζ | ξ)^(1/T), renormalised (flatter for T > 1: deterministic annealing); a fully
  annotated path's is its log P(ζ, ξ) at every T.

  Args:
    inputs: StackInputs. procedures, counters: [T, d] int annotation or None. (As forward_backward's.)
    temperature: [] a finite number > 0; 1 is the log-likelihood itself.
  Returns:
    [] log P(ξ) (of the paths that agree with the annotation), or its tempered form.
  """
  prepared = _prepared(inputs, procedures, counters)
  check_temperature(temperature)
  if isinstance(temperature, (int, float)) and temperature == 1:
    return _annotated_log_likelihood(*prepared)
  inputs, *rest = prepared
  return temperature * _annotated_log_likelihood(jax.tree.map(lambda x: x / temperature, inputs), *rest)


def forward_backward(inputs: StackInputs, procedures=None, counters=None) -> StackPosterior:
  """Exact log P(ξ) and every level's posterior frame marginals of one demonstration.

  jax.grad of log_likelihood is the posterior of each event, for example ∂/∂ log_act = marginals[d-1] and
  ∂/∂ log_stop[i] + ∂/∂ log_cont[i] = P(frame (h, τ) of level i at t, and every level below i stops at t).
  Memory is linear in T (O(T·S)). Batch with jax.vmap.

  Args:
    inputs: StackInputs: log_call d−1 arrays [T, K_i, C_i, K_{i+1}], log_act [T, K_{d-1}, C_{d-1}], log_stop
      and log_cont d arrays [T, K_i, C_i], length [] int in 1..T or None (= T). (Module docstring.)
    procedures, counters: [T, d] int annotation, root first, −1 = unknown (either may be None); paths must
      agree with every known entry. Fully annotated, log_likelihood is the complete-data log-likelihood of
      that path; ignored on padding.
  Returns:
    StackPosterior(log_likelihood [], marginals: d arrays [T, K_i, C_i]).
  """
  return StackPosterior(*_posterior(*_prepared(inputs, procedures, counters)))


@jax.jit
def _viterbi(inputs: StackInputs, procedures, counters, length):
  potentials = annotation_potentials(inputs, procedures, counters)
  log_increments, backpointers = forward(inputs, potentials, length, semiring_max=True)
  capacities = tuple(x.shape[2] for x in inputs.log_stop)
  path_procedures, path_counters, _ = backtrack(backpointers, length, capacities,
                                                 lambda level, pointer, rank, t: (pointer, 0.0, rank),
                                                 inputs.log_act.dtype)
  log_prob = jnp.sum(log_increments)
  return StackPath(*no_frame_unless_explained(log_prob, path_procedures, path_counters), log_prob)


def viterbi(inputs: StackInputs, procedures=None, counters=None) -> StackPath:
  """The most likely whole-stack path (max-product forward, per-level backpointers, backtrack).

  Memory O(T · S / (K_{d-1} C_{d-1})) for the backpointers.

  Args:
    inputs: StackInputs. procedures, counters: [T, d] int annotation or None. (As forward_backward's.)
  Returns:
    StackPath(procedures [T, d], counters [T, d], log_prob []); where no path explains the actions, log_prob
    −inf and NO_FRAME in every frame (as top_k).
  """
  return _viterbi(*_prepared(inputs, procedures, counters))


@jax.jit
def _sample_posterior(key, inputs: StackInputs, procedures, counters, length, temperature):
  """Backward sampling from the forward pass's stop scores of the lattice divided by temperature;
  log P(ζ, ξ) = temperature · (log P'(ξ) + Σ log P'(choice | ·)) with P' the tempered lattice's."""
  inputs = jax.tree.map(lambda x: x / temperature, inputs)
  potentials = annotation_potentials(inputs, procedures, counters)
  log_increments, stop_scores = forward(inputs, potentials, length, keep_stops=True)
  capacities = tuple(x.shape[2] for x in inputs.log_stop)

  def choose(level, scores, rank, t):
    scores = scores.reshape(-1)
    index = jax.random.categorical(jax.random.fold_in(jax.random.fold_in(key, t), level), scores)
    return index, scores[index] - logsumexp(scores), rank

  path_procedures, path_counters, log_posterior = backtrack(stop_scores, length, capacities, choose,
                                                             inputs.log_act.dtype)
  log_likelihood = jnp.sum(log_increments)
  log_prob = jnp.where(jnp.isfinite(log_likelihood), log_likelihood + log_posterior, -jnp.inf)
  return StackPath(*no_frame_unless_explained(log_likelihood, path_procedures, path_counters),
                   log_prob * temperature)



def sample_posterior(key, inputs: StackInputs, procedures=None, counters=None, temperature=1.0) -> StackPath:
  """One whole-stack path drawn exactly from P(ζ | ξ)^(1/temperature), renormalised (forward filter, backward
  sample): the posterior of the lattice with every input divided by temperature, as php_jax.sample_posterior.

  Step t draws with jax.random.fold_in(key, t). Vmap over keys for many samples.

  Args:
    key: a PRNG key. inputs: StackInputs. procedures, counters: [T, d] int annotation or None (as
      forward_backward's). temperature: [] a finite number > 0; 1 is the posterior itself.
  Returns:
    StackPath(procedures [T, d], counters [T, d], log_prob [] = log P(ζ, ξ) of the drawn path, untempered);
    where no path explains the actions, −inf and NO_FRAME in every frame.
  """
  check_key(key)
  prepared = _prepared(inputs, procedures, counters)
  check_temperature(temperature)
  return _sample_posterior(key, *prepared, temperature)


@functools.partial(jax.jit, static_argnums=0)
def _top_k(k: int, inputs: StackInputs, procedures, counters, length):
  log_prob, pointers = forward_top_k(k, inputs, annotation_potentials(inputs, procedures, counters), length)
  capacities = tuple(x.shape[2] for x in inputs.log_stop)

  def choose(level, pointer, rank, t):
    return pointer[rank] // k, 0.0, pointer[rank] % k

  path_procedures, path_counters, _ = jax.vmap(
      lambda rank: backtrack(pointers, length, capacities, choose, inputs.log_act.dtype, rank))(jnp.arange(k))
  return StackPath(*no_frame_unless_explained(log_prob[:, None, None], path_procedures, path_counters), log_prob)


def top_k(k: int, inputs: StackInputs, procedures=None, counters=None) -> StackPath:
  """The k most likely whole-stack paths, best first (k-best max-product; memory k times Viterbi's).

  If fewer than k paths are possible, the remaining entries have log_prob −inf and procedures = counters =
  NO_FRAME. Ties are broken deterministically.

  Args:
    k: int ≥ 1 (static). inputs: StackInputs. procedures, counters: [T, d] int annotation or None (as
      forward_backward's).
  Returns:
    StackPath(procedures [k, T, d], counters [k, T, d], log_prob [k]) descending; entry 0 is viterbi's.
  """
  k = check_k(k)
  return _top_k(k, *_prepared(inputs, procedures, counters, fill_unknown=True))


@jax.jit
def _entropy(p: StackInputs, procedures, counters, length):
  return entropy_and_events(p, annotation_potentials(p, procedures, counters), length)[0]


@jax.jit
def _entropies(p: StackInputs, p_annotation, q: StackInputs, q_annotation, length):
  """(H(p), H(p, q)) between the posteriors over paths; annotations are (procedures, counters) pairs.
  H(p, q) = log P_q(ξ) − E_p[log P_q(ζ, ξ)], the expectation from p's event posteriors: +inf where q rules
  out a path p allows; both 0 where p allows no path (sums over no paths)."""
  q_potentials = annotation_potentials(q, *q_annotation)
  entropy, events, log_z = entropy_and_events(p, annotation_potentials(p, *p_annotation), length)
  expected = expected_log_joint(events, (q, q_potentials))
  cross = jnp.where(jnp.isneginf(expected), jnp.inf, evidence(q, q_potentials, length) - expected)
  return entropy, jnp.where(jnp.isfinite(log_z), cross, 0.0)


def _named_arrays(inputs: StackInputs):
  """(name, array) of every array of inputs: log_call[0], ..., log_act, log_stop[0], ..., log_cont[d-1]."""
  for field in StackInputs._fields[:4]:
    value = getattr(inputs, field)
    yield from [(field, value)] if field == "log_act" else ((f"{field}[{i}]", x) for i, x in enumerate(value))


def _pair(p, q, p_annotation=(None, None), q_annotation=(None, None)):
  """Checks two lattices of the same shapes and length, and their annotations; returns _entropies' arguments."""
  checked = []
  for name, x, annotation in (("p", p, p_annotation), ("q", q, q_annotation)):
    as_inputs(name, x, StackInputs)
    try:
      x, *annotation, length = _prepared(x, *annotation, fill_unknown=True, name=name)
    except ValueError as error:
      raise ValueError(f"{name}: {error}") from None
    checked.append((x, tuple(annotation), length))
  (p, p_annotation, length), (q, q_annotation, q_length) = checked
  if len(p.log_stop) != len(q.log_stop):
    raise ValueError(f"p and q must have the same number of levels; got {len(p.log_stop)} and {len(q.log_stop)}")
  for (name, a), (_, b) in zip(_named_arrays(p), _named_arrays(q)):
    if jnp.shape(a) != jnp.shape(b):
      raise ValueError(f"p.{name} and q.{name} must have the same shape; got {jnp.shape(a)} and {jnp.shape(b)}")
  if not any(isinstance(x, jax.core.Tracer) for x in (length, q_length)) and int(length) != int(q_length):
    raise ValueError(f"p and q must have the same length; got {int(length)} and {int(q_length)}")
  return p, p_annotation, q, q_annotation, length


def posterior_entropy(inputs: StackInputs, procedures=None, counters=None) -> jax.Array:
  """Entropy of P(ζ | ξ) over whole-stack paths in nats: log P(ξ) − E[log P(ζ, ξ)], from the event posteriors;
  0 where no path explains ξ (a sum over no paths).

  Args:
    inputs: StackInputs. procedures, counters: [T, d] int annotation or None (as forward_backward's).
  Returns:
    [] nats.
  """
  return _entropy(*_prepared(inputs, procedures, counters, fill_unknown=True))


def cross_entropy(p: StackInputs, q: StackInputs) -> jax.Array:
  """H(p, q) = −Σ_ζ p(ζ | ξ) log q(ζ | ξ) in nats between the posteriors over whole-stack paths of two lattices
  of the same shapes and length: +inf where q rules out a path p allows, 0 where p allows none. Differentiable
  w.r.t. both.

  Args:
    p, q: StackInputs with the same shapes and length (checked when concrete). StackLattice(p,
      ...).cross_entropy(StackLattice(q, ...)) restricts either to an annotation.
  Returns:
    [] nats.
  """
  return _entropies(*_pair(p, q))[1]


def kl_divergence(p: StackInputs, q: StackInputs) -> jax.Array:
  """KL(p ‖ q) = H(p, q) − H(p) in nats between the posteriors over whole-stack paths: ≥ 0, 0 iff they agree,
  +inf where q rules out a path p allows, 0 where p allows none. Differentiable w.r.t. both.

  Args:
    p, q: StackInputs with the same shapes and length (checked when concrete).
  Returns:
    [] nats.
  """
  entropy, cross = _entropies(*_pair(p, q))
  return cross - entropy


class StackLattice(LatticeStructure):
  """The whole-stack lattice of one demonstration as a structure with queries (SynJax's distribution API;
  the same methods as php_jax.TwoLevelLattice): the posterior over whole-stack paths P(ζ | ξ), restricted to
  the paths that agree with the annotation. A frozen pytree: pass it through jit and vmap.

  Args:
    inputs: StackInputs (module docstring).
    procedures, counters: [T, d] int annotation, root first, −1 = unknown, or None (as forward_backward's).
  Raises:
    ValueError on construction, naming the argument (module docstring).
  Example:
    >>> lattice = StackLattice(inputs, procedures=known)
    >>> lattice.log_partition(), lattice.top_k(3).log_prob, lattice.kl_divergence(StackLattice(other))
  """

  def _checked(self):
    inputs, length = _check_inputs(self.inputs)
    return inputs, *_check_annotation(inputs, self.procedures, self.counters, length)

  def _annotation(self):
    return {"procedures": self.procedures, "counters": self.counters}

  def log_partition(self) -> jax.Array:
    """[] log P(ξ) (of the agreeing paths): the forward pass only."""
    return log_likelihood(self.inputs, **self._annotation())

  def posterior(self) -> StackPosterior:
    """forward_backward: StackPosterior(log_likelihood [], marginals: d arrays [T, K_i, C_i])."""
    return forward_backward(self.inputs, **self._annotation())

  def marginals(self) -> tuple:
    """d arrays [T, K_i, C_i] P(h_{i,t} = h, τ_{i,t} = τ | ξ)."""
    return self.posterior().marginals

  def argmax(self) -> StackPath:
    """The most likely path (viterbi): procedures, counters [T, d], log_prob []."""
    return viterbi(self.inputs, **self._annotation())

  def top_k(self, k: int) -> StackPath:
    """The k most likely paths, best first: procedures, counters [k, T, d], log_prob [k]."""
    return top_k(k, self.inputs, **self._annotation())

  def sample(self, key, temperature=1.0) -> StackPath:
    """One exact draw from P(ζ | ξ)^(1/temperature), renormalised; log_prob [] untempered log P(ζ, ξ)."""
    return sample_posterior(key, self.inputs, temperature=temperature, **self._annotation())

  def entropy(self) -> jax.Array:
    """[] H(P(ζ | ξ)) in nats."""
    return posterior_entropy(self.inputs, **self._annotation())

  def cross_entropy(self, other: StackLattice) -> jax.Array:
    """[] H(self, other) in nats between the posteriors over paths (same shapes and length); +inf where
    other rules out a path self allows."""
    other = self._same_kind(other)
    return _entropies(*_pair(self.inputs, other.inputs, (self.procedures, self.counters),
                             (other.procedures, other.counters)))[1]

  def kl_divergence(self, other: StackLattice) -> jax.Array:
    """[] KL(self ‖ other) in nats between the posteriors over paths (same shapes and length)."""
    other = self._same_kind(other)
    entropy, cross = _entropies(*_pair(self.inputs, other.inputs, (self.procedures, self.counters),
                                       (other.procedures, other.counters)))
    return cross - entropy
