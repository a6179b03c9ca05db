"""Demonstrations: observations, elementary actions and (when annotated) the whole call stack per step."""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from php_jax.executor import Rollout
from php_jax.hierarchy import HierarchySpec

UNKNOWN = -1  # procedure / counter value where the stack is not annotated, and on padding.


class Demonstration(NamedTuple):
  """One demonstration (a batch has a leading axis B). T = padded length, d = levels.

  Attributes:
    observations: [T+1, obs_dim] o_0 .. o_length (zero after): real numbers in any dtype that holds them exactly
      (the file readers give the narrowest, `compact_dtype`); the networks read them as float32.
    actions: [T, num_factors] int32 elementary actions.
    procedures: [T, d] int32 procedure per level at each step; UNKNOWN where not annotated or padding.
    counters: [T, d] int32 τ per level at each step; UNKNOWN where not annotated or padding.
    length: [] int32 steps used.
    strong: [] bool whether training may use the annotation, complete or partial (weak demonstrations may
      still carry the supervisor's stack, for measuring how well decoding recovers it).
  """
  observations: jax.Array
  actions: jax.Array
  procedures: jax.Array
  counters: jax.Array
  length: jax.Array
  strong: jax.Array


OBSERVATION_DTYPES = ("uint8", "int8", "uint16", "int16", "float16", "float32")  # narrowest first
_CHECKED_ROWS = 1 << 16  # rows compared at a time, so that the check holds little more than its input


def compact_dtype(observations: np.ndarray) -> np.dtype:
  """The narrowest of OBSERVATION_DTYPES that holds every value of observations [..., D] (as float32) bit for
  bit (-0.0 is no integer): where observations are small integers, a quarter (uint8, int8) or a half of float32's
  memory."""
  values = np.asarray(observations).reshape(-1, np.shape(observations)[-1])
  candidates = [np.dtype(name) for name in OBSERVATION_DTYPES[:-1]]
  for start in range(0, len(values), _CHECKED_ROWS):
    chunk = values[start:start + _CHECKED_ROWS].astype(np.float32)
    candidates = [dtype for dtype in candidates if _holds(dtype, chunk)]
  return candidates[0] if candidates else np.dtype(np.float32)


def _holds(dtype: np.dtype, values: np.ndarray) -> bool:
  """Whether dtype gives back float32 values bit for bit."""
  if dtype.kind in "iu" and values.size:
    info = np.iinfo(dtype)
    if not (values.min() >= info.min and values.max() <= info.max):
      return False
  with np.errstate(over="ignore", invalid="ignore"):
    return np.array_equal(values.astype(dtype).astype(np.float32).view(np.uint32), values.view(np.uint32))


def compacted(batch: Demonstration) -> Demonstration:
  """batch with its observations in `compact_dtype` (host side)."""
  observations = np.asarray(batch.observations)
  return batch._replace(observations=observations.astype(compact_dtype(observations), copy=False))


def from_rollouts(rollouts: Rollout, strong) -> Demonstration:
  """A batch of recorded rollouts [B, S, ...] → demonstrations trimmed to the longest episode (host side).

  Raises ValueError if the rollouts were not recorded, strong is neither one bool nor [B] bools, or an episode
  did not terminate or took an invalid action.
  """
  if rollouts.observations is None:
    raise ValueError("rollouts must be recorded (executor.rollout_batch(..., record=True)); got rollouts without "
                     "observations")
  length = np.asarray(rollouts.length)
  if np.shape(strong) not in ((), length.shape):
    raise ValueError(f"strong must be one bool or [B] = {list(length.shape)} bools; got shape {list(np.shape(strong))}")
  bad = np.flatnonzero(~np.asarray(rollouts.terminated))
  if bad.size:
    raise ValueError(f"rollouts {bad.tolist()} did not end with the root returning; cannot demonstrate")
  num_steps = int(length.max())
  pad = np.arange(num_steps)[None, :, None] >= length[:, None, None]
  return Demonstration(
      observations=jnp.asarray(np.asarray(rollouts.observations)[:, :num_steps + 1]),
      actions=jnp.asarray(np.asarray(rollouts.actions)[:, :num_steps]),
      procedures=jnp.asarray(np.where(pad, UNKNOWN, np.asarray(rollouts.procedures)[:, :num_steps])),
      counters=jnp.asarray(np.where(pad, UNKNOWN, np.asarray(rollouts.counters)[:, :num_steps])),
      length=jnp.asarray(length, jnp.int32),
      strong=jnp.broadcast_to(jnp.asarray(strong, bool), length.shape))


def _stack_error(prev_procs, prev_taus, procs, taus) -> str | None:
  """Why stack (procs, taus) cannot follow (prev_procs, prev_taus) after one action, or None if it can.

  Exactly one level j resumes: levels above it keep their frames, level j keeps its procedure with τ + 1,
  and every level below it is a fresh push with τ = 0.
  """
  depth = len(procs)
  for j in range(depth - 1, -1, -1):
    if (np.array_equal(procs[:j], prev_procs[:j]) and np.array_equal(taus[:j], prev_taus[:j])
        and procs[j] == prev_procs[j] and taus[j] == prev_taus[j] + 1 and np.all(taus[j + 1:] == 0)):
      return None
  changed = [i for i in range(depth) if (procs[i], taus[i]) != (prev_procs[i], prev_taus[i])]
  level = changed[0] if changed else depth - 1
  return (f"level {level} goes from (procedure {prev_procs[level]}, counter {prev_taus[level]}) to "
          f"(procedure {procs[level]}, counter {taus[level]}): counters must increment by one at the "
          f"resuming level, restart at 0 below it, and stay put above it")


def validate(batch: Demonstration, spec) -> None:
  """Checks a batch of demonstrations [B, ...] against a HierarchySpec (host side).

  Raises ValueError naming the demonstration and step of the first problem: shapes, lengths over capacity,
  actions or procedure ids out of range, or annotated stacks that break the call-stack semantics. A strong
  demonstration may leave stack entries UNKNOWN (partial annotation).
  """
  if not isinstance(spec, HierarchySpec):
    raise ValueError(f"spec must be a HierarchySpec; got {spec!r}")
  actions = np.asarray(batch.actions)
  procs, taus = np.asarray(batch.procedures), np.asarray(batch.counters)
  lengths, strong = np.asarray(batch.length), np.asarray(batch.strong)
  num_demos, num_steps = actions.shape[:2]
  expected = {"observations": (num_demos, num_steps + 1, spec.obs_dim),
              "actions": (num_demos, num_steps, len(spec.action_sizes)),
              "procedures": (num_demos, num_steps, spec.num_levels),
              "counters": (num_demos, num_steps, spec.num_levels), "length": (num_demos,),
              "strong": (num_demos,)}
  for name, shape in expected.items():
    if np.shape(getattr(batch, name)) != shape:
      raise ValueError(f"demonstrations.{name} has shape {np.shape(getattr(batch, name))}; expected {shape}")
  for b in range(num_demos):
    length = int(lengths[b])
    if not 1 <= length <= num_steps:
      raise ValueError(f"demonstration {b}: length {length} is outside 1..{num_steps} (the capacity)")
    bad = np.argwhere((actions[b, :length] < 0) | (actions[b, :length] >= np.array(spec.action_sizes)))
    if bad.size:
      t, f = bad[0]
      raise ValueError(f"demonstration {b}, step {t}: action factor {f} = {actions[b, t, f]} is outside "
                       f"0..{spec.action_sizes[f] - 1}")
    if strong[b]:
      error = stack_error(procs[b, :length], taus[b, :length], spec)
      if error:
        raise ValueError(f"demonstration {b}, {error}")


def stack_error(procs: np.ndarray, taus: np.ndarray, spec) -> str | None:
  """Why an annotated stack [length, d] (UNKNOWN where not annotated) is impossible, or None.

  Known entries must be in range (a procedure with its counter), counters start at 0, and consecutive
  steps whose whole stacks are known must follow the call-stack semantics.
  """
  known = (procs != UNKNOWN) & (taus != UNKNOWN)
  half = np.argwhere((procs != UNKNOWN) != (taus != UNKNOWN))
  if half.size:
    t, level = half[0]
    return f"step {t}: level {level} has a procedure without a counter or a counter without a procedure"
  for t in range(len(procs)):
    for level in range(spec.num_levels):
      if known[t, level] and not 0 <= procs[t, level] < spec.num_procs(level):
        return (f"step {t}: procedure id {procs[t, level]} at level {level} is unknown (level {level} has "
                f"{spec.num_procs(level)} procedures)")
      if known[t, level] and taus[t, level] < 0:
        return f"step {t}: counter {taus[t, level]} at level {level} is negative"
    if t == 0 and np.any(taus[0][known[0]] != 0):
      return f"step 0: counters must start at 0; got {taus[0].tolist()}"
    if t > 0 and known[t - 1].all() and known[t].all():
      error = _stack_error(procs[t - 1], taus[t - 1], procs[t], taus[t])
      if error:
        return f"step {t}: {error}"
  return None
