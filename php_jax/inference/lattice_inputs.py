"""The two-level lattice's inputs and results, and the checks every E-step function makes of its arguments.

`LatticeInputs` is one demonstration's lattice (log_root [T, K]; log_op, log_stop, log_cont [T, K, C]; length),
`LatticePosterior` and `LatticePath` what the E-step returns (`php_jax.inference.lattice`, whose docstring says
what each array means). Every E-step function accepts the five arrays or one LatticeInputs (`accepts_inputs`).
`LatticeStructure` is the base of the lattices as structures (TwoLevelLattice, StackLattice). The checks refuse,
with a ValueError naming the argument, what the lattice module's docstring lists; `annotate` restricts a lattice
to an annotation.
"""
from __future__ import annotations

import dataclasses
import functools
import inspect
import operator
import warnings
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

NO_FRAME = -1  # procedure / counter value of padding steps in a LatticePath.


class LatticeInputs(NamedTuple):
  """One demonstration's lattice, the five arguments of every E-step function in order: pass it whole,
  `forward_backward(inputs)`, or unpacked, `forward_backward(*inputs)`.

  Attributes:
    log_root: [T, K]. log_op, log_stop, log_cont: [T, K, C]. length: [] int or None (= T). (php_jax.inference.lattice's docstring.)
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
  """One latent path through the lattice, named as the stack lattice's paths and as an annotation:
  `forward_backward(inputs, procedures=path.procedures, counters=path.counters)`.

  Attributes:
    procedures: [T] int32 h_t, NO_FRAME on padding (and at every step where no path explains the actions).
    counters: [T] int32 τ_t, NO_FRAME where procedures is.
    log_prob: [] log P(ζ, ξ) of the path (its complete-data log-likelihood).
  """
  procedures: jax.Array
  counters: jax.Array
  log_prob: jax.Array

  @property
  def procedure(self) -> jax.Array:
    """Deprecated: `procedures`, the name both lattices use."""
    warnings.warn("LatticePath.procedure is deprecated; use LatticePath.procedures", DeprecationWarning,
                  stacklevel=2)
    return self.procedures

  @property
  def counter(self) -> jax.Array:
    """Deprecated: `counters`, the name both lattices use."""
    warnings.warn("LatticePath.counter is deprecated; use LatticePath.counters", DeprecationWarning, stacklevel=2)
    return self.counters


def no_frame_unless_explained(log_likelihood, *frames) -> tuple:
  """Each of frames, NO_FRAME where no path explains the actions (log_likelihood −inf, [] or one per path, shaped
  to broadcast against the frames): a decoded, sampled or k-th best path that does not exist."""
  impossible = jnp.isneginf(log_likelihood)
  return tuple(jnp.where(impossible, NO_FRAME, x) for x in frames)


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
  checks shapes and dtypes, and values when concrete (php_jax.inference.lattice's docstring); jit and vmap rebuild it unchecked.

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


def in_common_dtype(*arrays):
  """The arrays (or nested lists) as arrays of their common (promoted) dtype, float16 and bfloat16 as float32
  (php_jax.inference.lattice's docstring, Dtypes): the public E-step functions compute in one dtype of at least float32. The
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


def check_inputs(log_root, log_op, log_stop, log_cont, length):
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


def annotated_log_op(log_op, procedures, counters, length):
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
  _, _, _, length = check_inputs(log_root, log_op, log_stop, log_cont, length)
  check_finite(arrays)
  return LatticeInputs(log_root, log_op, log_stop, log_cont, int(length))


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
