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
keyword); results name the frame marginals `marginals`, a path's frames `procedures`, `counters` and its
log P(ζ, ξ) `log_prob` (here aliases of v, procedure, counter). `php_jax.TwoLevelLattice(inputs, procedures,
counters)` (php_jax.inference.lattice_ops) answers the same queries as `php_jax.StackLattice`.

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

import dataclasses
import functools
import inspect
import operator
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

NO_FRAME = -1  # procedure / counter value of padding steps in a LatticePath.


class LatticeInputs(NamedTuple):
  """One demonstration's lattice, the five arguments of every E-step function in order: pass it whole,
  `forward_backward(inputs)`, or unpacked, `forward_backward(*inputs)`.

  Attributes:
    log_root: [T, K]. log_op, log_stop, log_cont: [T, K, C]. length: [] int or None (= T). (Module docstring.)
  """
  log_root: jax.Array
  log_op: jax.Array
  log_stop: jax.Array
  log_cont: jax.Array
  length: Any = None


class LatticePosterior(NamedTuple):
  """Result of `forward_backward`.

  Attributes:
    log_likelihood: [] log P(ξ), up to the causal dynamics factor; −inf if no path is possible.
    v: [T, K, C] P(h_t = h, τ_t = τ | ξ); zero on padding. Also `marginals`, the stack lattice's name.
    w: [T, K, C] P(h_t = h, τ_t = τ, τ_{t+1} = τ + 1 | ξ); zero on padding and at the last step.
  """
  log_likelihood: jax.Array
  v: jax.Array
  w: jax.Array

  @property
  def marginals(self) -> jax.Array:
    """[T, K, C] v, the frame marginals."""
    return self.v


class LatticePath(NamedTuple):
  """One latent path through the lattice.

  Attributes:
    procedure: [T] int32 h_t, NO_FRAME on padding. Also `procedures`, the stack lattice's name.
    counter: [T] int32 τ_t, NO_FRAME on padding. Also `counters`.
    log_prob: [] log P(ζ, ξ) of the path (its complete-data log-likelihood).
  """
  procedure: jax.Array
  counter: jax.Array
  log_prob: jax.Array

  @property
  def procedures(self) -> jax.Array:
    """[T] procedure, named as an annotation: `forward_backward(inputs, path.procedures, path.counters)`."""
    return self.procedure

  @property
  def counters(self) -> jax.Array:
    """[T] counter."""
    return self.counter


def accepts_inputs(fn):
  """Lets fn, whose parameters include the five lattice arrays log_root .. length, take one LatticeInputs in
  log_root's place: the positional arguments after it fill fn's other parameters in order, so that
  complete_log_likelihood(inputs, procedure, counter) is complete_log_likelihood(*inputs[:4], procedure,
  counter, inputs.length)."""
  names = list(inspect.signature(fn).parameters)
  first = names.index("log_root")
  others = [name for name in names[first:] if name not in LatticeInputs._fields]

  @functools.wraps(fn)
  def wrapped(*args, **kwargs):
    if len(args) <= first or not isinstance(args[first], LatticeInputs):
      return fn(*args, **kwargs)
    rest = args[first + 1:]
    if len(rest) > len(others):
      raise TypeError(f"{fn.__name__} takes at most {len(others)} positional arguments after a LatticeInputs "
                      f"({', '.join(others)}); got {len(rest)}")
    return fn(*args[:first], **args[first]._asdict(), **dict(zip(others, rest)), **kwargs)

  return wrapped


@dataclasses.dataclass(frozen=True, eq=False)
class LatticeStructure:
  """Base of php_jax.TwoLevelLattice and php_jax.StackLattice: one demonstration's lattice and annotation, a
  frozen pytree (it passes through jit and vmap; batch by building it inside vmap). Built once: construction
  checks shapes and dtypes, and values when concrete (module docstring); jit and vmap rebuild it unchecked.

  Attributes:
    inputs: the lattice (LatticeInputs or StackInputs).
    procedures, counters: the annotation, int, −1 = unknown, or None.
  """
  inputs: Any
  procedures: Any = None
  counters: Any = None

  def __init_subclass__(cls, **kwargs):
    super().__init_subclass__(**kwargs)
    jax.tree_util.register_pytree_node_class(cls)

  def __post_init__(self):
    for name, value in zip(("inputs", "procedures", "counters"), self._checked()):
      object.__setattr__(self, name, value)

  def _checked(self):
    """(inputs, procedures, counters) checked and as arrays; raises ValueError naming the argument."""
    raise NotImplementedError

  def _same_kind(self, other):
    """other, refused unless it is a structure of this kind (for kl_divergence and cross_entropy)."""
    if type(other) is not type(self):
      raise ValueError(f"other must be a {type(self).__name__}; got a {type(other).__name__}")
    return other

  def tree_flatten(self):
    return (self.inputs, self.procedures, self.counters), None

  @classmethod
  def tree_unflatten(cls, _, children):
    structure = object.__new__(cls)
    for name, value in zip(("inputs", "procedures", "counters"), children):
      object.__setattr__(structure, name, value)
    return structure


_HALF_PRECISION = (jnp.dtype(jnp.float16), jnp.dtype(jnp.bfloat16))


def _in_common_dtype(*arrays):
  """The arrays (or nested lists) as arrays of their common (promoted) dtype, float16 and bfloat16 as float32
  (module docstring, Dtypes): the public E-step functions compute in one dtype of at least float32. The
  cast's gradient returns cotangents in the caller's dtype."""
  arrays = tuple(x if hasattr(x, "dtype") else jnp.asarray(x) for x in arrays)  # nested lists as arrays
  dtype = jnp.result_type(*arrays)
  dtype = jnp.dtype(jnp.float32) if dtype in _HALF_PRECISION else dtype
  return tuple(x.astype(dtype) if x.dtype != dtype else x for x in arrays)


def check_length(length, num_steps: int):
  """Refuses a length that is not an integer scalar (bool and float are not) or, when concrete, is outside
  1..T, with a message naming it. Returns the length as an int32 array (T if None)."""
  if length is None:
    return jnp.asarray(num_steps, jnp.int32)
  dtype = getattr(length, "dtype", None)
  integer = (isinstance(length, int) and not isinstance(length, bool)) or (
      dtype is not None and jnp.ndim(length) == 0 and jnp.issubdtype(dtype, jnp.integer))
  if not integer:
    shown = f"an array of shape {np.shape(length)}" if np.ndim(length) else repr(length)
    raise ValueError(f"length must be an integer in 1..T = 1..{num_steps}; got {shown}")
  if not isinstance(length, jax.core.Tracer) and not 1 <= int(length) <= num_steps:
    raise ValueError(f"length must be in 1..T = 1..{num_steps}; got {int(length)}")
  return jnp.asarray(length, jnp.int32)


def check_temperature(temperature):
  """Refuses a temperature that is not a scalar real number (bool, None and strings are not) or, when
  concrete, not finite and > 0."""
  try:
    dtype = jnp.result_type(temperature)
  except TypeError:
    dtype = jnp.dtype(object)
  real = jnp.issubdtype(dtype, jnp.floating) or jnp.issubdtype(dtype, jnp.integer)
  if temperature is None or isinstance(temperature, bool) or not real or jnp.ndim(temperature) != 0 or (
      not isinstance(temperature, jax.core.Tracer) and not (np.isfinite(temperature) and temperature > 0)):
    shown = f"an array of shape {np.shape(temperature)}" if np.ndim(temperature) else repr(temperature)
    raise ValueError(f"temperature must be a finite number > 0; got {shown}")


def check_k(k) -> int:
  """k as an int; refuses one that is not a concrete integer ≥ 1 (bool is not; a 0-d integer array is)."""
  try:
    index = None if isinstance(k, (bool, np.bool_)) else operator.index(k)
  except TypeError:  # a float, None, or a traced value (k is static)
    index = None
  if index is None or index < 1:
    raise ValueError(f"k must be an int ≥ 1; got {k!r}")
  return index


def check_key(key, name: str = "key", batched: bool = False):
  """Refuses a key that is not one PRNG key (batched: a batch [B] of them): a key array of shape [] or [B]
  (jax.random.key's, jax.random.split's), or a legacy uint32 key [n] or [B, n] (jax.random.PRNGKey's).
  Static: checked under jit too."""
  dtype = getattr(key, "dtype", None)
  typed = dtype is not None and jax.dtypes.issubdtype(dtype, jax.dtypes.prng_key)
  if not ((typed and jnp.ndim(key) == batched) or (dtype == jnp.uint32 and jnp.ndim(key) == batched + 1)):
    shown = f"an array of dtype {dtype} and shape {jnp.shape(key)}" if dtype is not None else repr(key)
    what = ("a batch [B] of PRNG keys (jax.random.split(key, B))" if batched
            else "one PRNG key (jax.random.key(seed); vmap over keys for many)")
    raise ValueError(f"{name} must be {what}; got {shown}")


def check_log_probs(name: str, x, shape: str):
  """x as an array (a nested list of floats becomes one); refuses, naming it, anything but a float array
  (None, integer and boolean arrays). shape: the expected shape in words, for the message."""
  if not hasattr(x, "dtype"):
    try:
      x = jnp.asarray(x)
    except (TypeError, ValueError):
      raise ValueError(f"{name} must be a float array {shape}; got {described(x)}") from None
  if not jnp.issubdtype(x.dtype, jnp.floating):
    raise ValueError(f"{name} must be a float array {shape} of log-probabilities; got dtype {x.dtype}")
  return x


def check_finite(arrays: dict, length=None):
  """Refuses NaN or +inf (−inf is a legal zero probability) in any of arrays (name → [T, ...] array) on the
  steps before length (every step if None), naming the array and the index; nothing is checked when any of
  them or length is traced (under jit or vmap)."""
  if any(isinstance(x, jax.core.Tracer) for x in (*arrays.values(), length)):
    return
  for name, x in arrays.items():
    values = np.asarray(x)[:None if length is None else int(length)]
    for bad, what in ((np.isnan(values), "NaN"), (np.isposinf(values), "+inf")):
      if bad.any():
        raise ValueError(f"{name} contains {what} at index {tuple(int(i) for i in np.argwhere(bad)[0])}")


def as_inputs(name: str, inputs, kind):
  """inputs as a `kind` (LatticeInputs or StackInputs): one, or a plain tuple or list of its fields (length
  optional); refuses anything else (None, the other lattice's inputs), naming it."""
  if isinstance(inputs, kind):
    return inputs
  if isinstance(inputs, (tuple, list)) and not hasattr(inputs, "_fields") and len(inputs) in (4, 5):
    return kind(*inputs)
  raise ValueError(f"{name} must be a {kind.__name__} ({', '.join(kind._fields)}); got {described(inputs)}")


def described(x) -> str:
  """What x is, for a refusal: "None", "an array of shape (3, 2)", "a tuple of 3", "a str"."""
  if x is None:
    return "None"
  if hasattr(x, "shape"):
    return f"an array of shape {tuple(x.shape)}"
  return f"a {type(x).__name__}" + (f" of {len(x)}" if isinstance(x, (tuple, list)) else "")


def check_annotation(name: str, values, shape: tuple, bounds, length=None):
  """Refuses an annotation that is not an integer array of `shape` or, when concrete, has a value outside
  −1..size−1 on a step before `length` (every step if None), naming the entry.

  Args:
    values: [T] (bounds: one (letter, size) pair) or [T, d] (bounds: one pair per level), or a list.
  Returns:
    values as an array.
  """
  values = values if hasattr(values, "dtype") else np.asarray(values)
  if not jnp.issubdtype(values.dtype, jnp.integer):
    raise ValueError(f"{name} must be an integer array (−1 = unknown); got dtype {values.dtype}")
  if jnp.shape(values) != shape:
    raise ValueError(f"{name} must have shape {shape}; got {jnp.shape(values)}")
  if isinstance(values, jax.core.Tracer) or isinstance(length, jax.core.Tracer):
    return values
  used = np.asarray(values)[:None if length is None else int(length)].reshape(-1, len(bounds))
  for level, (letter, size) in enumerate(bounds):
    bad = np.flatnonzero((used[:, level] < -1) | (used[:, level] >= size))
    if bad.size:
      entry = f"{bad[0]}" if len(shape) == 1 else f"{bad[0]}, {level}"
      raise ValueError(f"{name}[{entry}] = {int(used[bad[0], level])} is outside −1..{letter}−1 = −1..{size - 1}")
  return values


def _check_inputs(log_root, log_op, log_stop, log_cont, length):
  """Validates dtypes and shapes (static), the length and, when concrete, the values on the steps before it
  (no NaN or +inf); returns (T, K, C, length as an int32 array)."""
  arrays = {"log_root": check_log_probs("log_root", log_root, "[T, K]")}
  arrays.update((name, check_log_probs(name, x, "[T, K, C]"))
                for name, x in (("log_op", log_op), ("log_stop", log_stop), ("log_cont", log_cont)))
  log_root, log_op, log_stop, log_cont = arrays.values()
  if jnp.ndim(log_op) != 3:
    raise ValueError(f"log_op must be [T, K, C]; got shape {jnp.shape(log_op)}")
  num_steps, num_procs, capacity = jnp.shape(log_op)
  if min(num_steps, num_procs, capacity) < 1:
    raise ValueError(f"T, K and C must be ≥ 1; log_op has shape {jnp.shape(log_op)}")
  for name, arr in (("log_stop", log_stop), ("log_cont", log_cont)):
    if jnp.shape(arr) != jnp.shape(log_op):
      raise ValueError(f"{name} must have log_op's shape [T, K, C] = {jnp.shape(log_op)}; "
                       f"got {jnp.shape(arr)}")
  if jnp.shape(log_root) != (num_steps, num_procs):
    raise ValueError(f"log_root must be [T, K] = {(num_steps, num_procs)}; got {jnp.shape(log_root)}")
  checked = check_length(length, num_steps)
  check_finite(arrays, checked)
  return num_steps, num_procs, capacity, checked


def _annotated(log_op, procedures, counters, length):
  """log_op restricted to the annotation (procedures, counters [T] or None), checked on the steps before length."""
  if procedures is None and counters is None:
    return log_op
  num_steps, num_procs, capacity = jnp.shape(log_op)
  unknown = jnp.full(num_steps, -1, jnp.int32)
  procedures = unknown if procedures is None else check_annotation(
      "procedures", procedures, (num_steps,), [("K", num_procs)], length)
  counters = unknown if counters is None else check_annotation(
      "counters", counters, (num_steps,), [("C", capacity)], length)
  return _mask(log_op, procedures, counters)


@accepts_inputs
def validate_inputs(log_root, log_op, log_stop, log_cont, length=None) -> LatticeInputs:
  """Checks one demonstration's lattice concretely (outside jit), with a message naming the argument.

  Checks: log_op, log_stop, log_cont are float arrays [T, K, C] and log_root [T, K] with T, K, C ≥ 1 (integer
  or boolean arrays and Python lists are refused: pass jnp.asarray(x, jnp.float32)); no NaN and no +inf
  (−inf is a legal zero probability); length, if given, an integer (Python, NumPy or a 0-d integer array)
  in 1..T. The E-step functions check the same themselves on concrete values, but take nested lists and look
  for NaN and +inf only on the steps before length; under jit or vmap they check shapes and dtypes only.

  Args:
    log_root: [T, K]. log_op, log_stop, log_cont: [T, K, C]. length: [] int or None (= T). Or one LatticeInputs.
  Returns:
    LatticeInputs with length as a Python int.
  Raises:
    ValueError on the first problem found. TypeError for traced values.
  """
  arrays = {"log_root": log_root, "log_op": log_op, "log_stop": log_stop, "log_cont": log_cont}
  for name, x in arrays.items():
    if isinstance(x, jax.core.Tracer):
      raise TypeError(f"validate_inputs needs concrete values; {name} is traced (call it outside jit/vmap)")
    if not hasattr(x, "dtype"):
      raise ValueError(f"{name} must be a float array; got a {type(x).__name__} "
                       f"(pass jnp.asarray({name}, jnp.float32))")
    if not jnp.issubdtype(x.dtype, jnp.floating):
      raise ValueError(f"{name} must be a float array; got dtype {x.dtype}")
  if isinstance(length, jax.core.Tracer):
    raise TypeError("validate_inputs needs concrete values; length is traced (call it outside jit/vmap)")
  _, _, _, length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  check_finite(arrays)
  return LatticeInputs(log_root, log_op, log_stop, log_cont, int(length))


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
      stop_total = jnp.log(total) + peak
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
  _, _, _, length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = _annotated(log_op, procedures, counters, length)
  return LatticePosterior(*_posterior_jit(*_in_common_dtype(log_root, log_op, log_stop, log_cont), length))


@accepts_inputs
def viterbi(log_root, log_op, log_stop, log_cont, length=None, procedures=None, counters=None) -> LatticePath:
  """Most likely latent path (max-product forward, one backpointer per step).

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the first five).
  Returns:
    LatticePath(procedure [T], counter [T], log_prob []).
  """
  _, _, _, length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = _annotated(log_op, procedures, counters, length)
  return _viterbi(*_in_common_dtype(log_root, log_op, log_stop, log_cont), length)


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
  return _path_from_states(states, capacity, jnp.sum(log_increments))


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
    LatticePath(procedure [T], counter [T], log_prob []): log_prob is log P(ζ, ξ) under the untempered model.
  Example:
    >>> path = sample_posterior(jax.random.key(0), log_root, log_op, log_stop, log_cont, 5, temperature=0.5)
  """
  check_key(key)
  _, _, _, length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  check_temperature(temperature)
  log_op = _annotated(log_op, procedures, counters, length)
  return _sample_posterior(key, *_in_common_dtype(log_root, log_op, log_stop, log_cont), length, temperature)


@jax.jit
def _sample_posterior(key, log_root, log_op, log_stop, log_cont, length, temperature):
  num_steps, _, capacity = log_op.shape
  tempered = (x / temperature for x in (log_root, log_op, log_stop, log_cont))
  _, stop_filter = _forward_filter(*tempered, length)

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
  path = _path_from_states(states, capacity, jnp.zeros(()))
  return path._replace(log_prob=_complete_log_likelihood(
      log_root, log_op, log_stop, log_cont, path.procedure, path.counter, length))


def max_marginal_path(posterior: LatticePosterior, length=None) -> LatticePath:
  """Per step the most probable (h, τ) under v. Not always a valid path; log_prob is not computed (NaN).

  Args:
    posterior: forward_backward's result (v [T, K, C]). length: [] int in 1..T, default T (as
      forward_backward's: a traced one is not range-checked).
  Returns:
    LatticePath(procedure [T], counter [T], log_prob [] NaN).
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
  num_steps, num_procs, capacity, length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  procedure = check_annotation("procedure", procedure, (num_steps,), [("K", num_procs)], length)
  counter = check_annotation("counter", counter, (num_steps,), [("C", capacity)], length)
  return _complete_log_likelihood(*_in_common_dtype(log_root, log_op, log_stop, log_cont), procedure, counter, length)


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


def annotate(log_op, procedure, counter):
  """Restricts the lattice to annotated frames: strong, weak or partial supervision in one code path.

  Every path visits exactly one cell per step, so masking log_op outside the annotated cell keeps exactly
  the paths that agree with the annotation; forward_backward then returns the complete-data
  log-likelihood for a fully annotated demonstration and anything between for a partial one.

  Args:
    log_op: [T, K, C].
    procedure: [T] int, the annotated h_t in 0..K−1 or −1 where unknown.
    counter: [T] int, the annotated τ_t in 0..C−1 or −1 where unknown.
  Returns:
    [T, K, C] log_op with −inf outside the annotation.
  Raises:
    ValueError for a log_op that is not a float array [T, K, C], for a float or misshapen annotation and,
    when procedure or counter is concrete (not traced), for a value out of range at any step, naming the step.
  """
  log_op = check_log_probs("log_op", log_op, "[T, K, C]")
  if jnp.ndim(log_op) != 3:
    raise ValueError(f"log_op must be [T, K, C]; got shape {jnp.shape(log_op)}")
  num_steps, num_procs, capacity = log_op.shape
  procedure = check_annotation("procedure", procedure, (num_steps,), [("K", num_procs)])
  counter = check_annotation("counter", counter, (num_steps,), [("C", capacity)])
  return _mask(log_op, procedure, counter)


def _mask(log_op, procedure, counter):
  log_op = log_op if hasattr(log_op, "dtype") else jnp.asarray(log_op)
  _, num_procs, capacity = log_op.shape
  proc_ok = (procedure[:, None] < 0) | (procedure[:, None] == jnp.arange(num_procs)[None, :])
  tau_ok = (counter[:, None] < 0) | (counter[:, None] == jnp.arange(capacity)[None, :])
  return jnp.where(proc_ok[:, :, None] & tau_ok[:, None, :], log_op, -jnp.inf)


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
  """Entropy of P(ζ | ξ) in nats: log P(ξ) − E[log P(ζ, ξ)], from the marginals.

  Args:
    log_root [T, K], log_op, log_stop, log_cont [T, K, C], length [], procedures, counters [T]: as
      forward_backward (or one LatticeInputs for the first five).
  Returns:
    [] nats.
  """
  _, _, _, checked_length = _check_inputs(log_root, log_op, log_stop, log_cont, length)
  log_op = _annotated(log_op, procedures, counters, checked_length)
  inputs = _in_common_dtype(log_root, log_op, log_stop, log_cont)
  post = forward_backward(*inputs, length)
  return post.log_likelihood - _expected_log_joint(post, *inputs)


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
