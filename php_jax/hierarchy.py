"""What a hierarchy looks like: levels of procedures, each level's operation space, and the policy protocol
that oracles and learned PHPs share (so one executor runs both)."""
from __future__ import annotations

import dataclasses
from typing import Protocol

import jax
import numpy as np


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
  Raises:
    ValueError naming the field: no levels, a level without procedures, a root level of more than one,
    no action factors or one of size < 1, or a negative obs_dim (0: not known yet).
  """
  name: str
  levels: tuple[tuple[str, ...], ...]
  action_sizes: tuple[int, ...]
  obs_dim: int
  allowed_ops: tuple | None = None

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


class Policy(Protocol):
  """A hierarchy's statements. level is a static int; proc, tau are [] int32; obs is [obs_dim]."""

  def operation(self, level: int, proc: jax.Array, tau: jax.Array, obs: jax.Array,
                key: jax.Array) -> jax.Array:
    """η_proc^tau(obs): int32 [len(spec.op_sizes(level))], a callee [1] or an elementary action."""

  def terminates(self, level: int, proc: jax.Array, tau: jax.Array, obs: jax.Array,
                 key: jax.Array) -> jax.Array:
    """ψ_proc^tau(obs): [] bool, whether the frame returns after its operation number tau."""
