"""What a hierarchy looks like: levels of procedures, each level's operation space, and the policy protocol
that oracles and learned PHPs share (so one executor runs both)."""
from __future__ import annotations

import dataclasses
from typing import Protocol

import jax
import numpy as np

from php_jax import encoders


def check_size(name: str, value, least: int = 1) -> int:
  """value as an int; refuses, naming it, one that is not an integer ≥ least (bool and float are not, a NumPy
  integer is)."""
  if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)) or value < least:
    raise ValueError(f"{name} must be an integer ≥ {least}; got {value!r}")
  return int(value)


@dataclasses.dataclass(frozen=True)
class HierarchySpec:
  """Levels 0 (root) .. d-1 (lowest). Level i < d-1 calls level i+1's procedures; level d-1 takes
  elementary actions, a product of categoricals of sizes action_sizes.

  Attributes:
    name: task name.
    levels: procedure names per level; level 0 has the single root procedure.
    action_sizes: elementary action factor sizes, e.g. (2, 4, 10): three factors.
    obs_dim: observation size.
    allowed_ops: the call graph the hierarchy declares (a hierarchy file's "calls"): per level, root first,
      None or `[K_i][Σ op_sizes(i)]` bools, which operations each procedure may take (`php_jax.training.call_graph`);
      None: any, at every level.
    observes: which observation entries each procedure's networks see (a hierarchy file's "observes", state
      abstraction as in MAXQ): per level, root first, None or per procedure None (every entry) or a sorted
      tuple of entry indices; None: every entry, at every level.
    observation: what the observation's numbers are (`php_jax.encoders` fields, in order), which the levels'
      shared encoders read; None: numbers, each network reads them as they are.
  Raises:
    ValueError naming the field: no levels, a level without procedures, a root level of more than one,
    no action factors or one of size < 1, a negative obs_dim (0: not known yet), or observes of another
    shape or naming an entry outside 0..obs_dim−1 (once obs_dim is known), or observation fields whose sizes
    do not add up to obs_dim (once it is known).
  """
  name: str
  levels: tuple[tuple[str, ...], ...]
  action_sizes: tuple[int, ...]
  obs_dim: int
  allowed_ops: tuple | None = None
  observes: tuple | None = None
  observation: tuple | None = None

  def __post_init__(self):
    if not (isinstance(self.levels, tuple) and self.levels
            and all(isinstance(level, tuple) and level for level in self.levels)):
      raise ValueError(f"levels must be a non-empty tuple of non-empty tuples of procedure names, root first; "
                       f"got {self.levels!r}")
    if len(self.levels[0]) != 1:
      raise ValueError(f"levels: the root level has one procedure; got {self.levels[0]!r}")
    if not (isinstance(self.action_sizes, tuple) and self.action_sizes):
      raise ValueError(f"action_sizes must be a non-empty tuple of factor sizes; got {self.action_sizes!r}")
    for f, size in enumerate(self.action_sizes):
      check_size(f"action_sizes[{f}]", size)
    check_size("obs_dim", self.obs_dim, 0)
    if self.observes is not None:
      check_observes(self.observes, self.levels, self.obs_dim)
    if self.observes is not None and encoders.structured(self.observation):
      raise ValueError("observes: procedures that see different observation entries cannot share the encoder "
                       "that the observation's fields call for; drop \"observes\" or the fields")
    if self.observation is not None and self.obs_dim and encoders.size(self.observation) != self.obs_dim:
      raise ValueError(f"observation: its fields take {encoders.size(self.observation)} numbers where "
                       f"observations have {self.obs_dim}")

  @property
  def num_levels(self) -> int:
    return len(self.levels)

  def num_procs(self, level: int) -> int:
    return len(self.levels[level])

  def op_sizes(self, level: int) -> tuple[int, ...]:
    """Factor sizes of level's operations: the next level's procedures, or the elementary action."""
    if level == self.num_levels - 1:
      return self.action_sizes
    return (self.num_procs(level + 1),)


def check_observes(observes, levels: tuple[tuple[str, ...], ...], obs_dim: int) -> None:
  """Refuses (ValueError naming the procedure) observes that is not, per level, None or per procedure None or a
  sorted tuple of distinct entry indices, each in 0..obs_dim−1 when obs_dim is known (> 0)."""
  if not (isinstance(observes, tuple) and len(observes) == len(levels)):
    raise ValueError(f"observes must give one entry per level, root first ({len(levels)}); got {observes!r}")
  for level, (names, per_procedure) in enumerate(zip(levels, observes)):
    if per_procedure is None:
      continue
    if not (isinstance(per_procedure, tuple) and len(per_procedure) == len(names)):
      raise ValueError(f"observes[{level}] must give one entry per procedure ({len(names)}); got {per_procedure!r}")
    for name, entries in zip(names, per_procedure):
      if entries is None:
        continue
      if not (isinstance(entries, tuple) and all(isinstance(e, int) and not isinstance(e, bool) and e >= 0
                                                 for e in entries) and list(entries) == sorted(set(entries))):
        raise ValueError(f"observes: level {level}'s {name!r} must list distinct observation entries in "
                         f"increasing order; got {entries!r}")
      if obs_dim and entries and entries[-1] >= obs_dim:
        raise ValueError(f"observes: level {level}'s {name!r} names observation entry {entries[-1]}, outside "
                         f"0..{obs_dim - 1} (observations have {obs_dim} numbers)")


class Policy(Protocol):
  """A hierarchy's statements. level is a static int; proc, tau are [] int32; obs is [obs_dim]. A policy that
  remembers the episode (a learned hierarchy with a memory) also has initial_memory(), remember(memory, obs,
  previous_action) and recall(memory), the Policy that decides with it (`executor`)."""

  def operation(self, level: int, proc: jax.Array, tau: jax.Array, obs: jax.Array,
                key: jax.Array) -> jax.Array:
    """η_proc^tau(obs): int32 [len(spec.op_sizes(level))], a callee [1] or an elementary action."""

  def terminates(self, level: int, proc: jax.Array, tau: jax.Array, obs: jax.Array,
                 key: jax.Array) -> jax.Array:
    """ψ_proc^tau(obs): [] bool, whether the frame returns after its operation number tau."""
