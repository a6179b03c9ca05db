"""The supervisor's hierarchy for NanoCraft (paper §5.1), as a Policy of pure functions of
(level, procedure, τ, observation): nanocraft → {moves_r, moves_d, builds_r/d/l/u} → {move_r, move_d,
build_r/d/l/u} → elementary actions."""
from __future__ import annotations

import jax.numpy as jnp
from flax import struct

from php_jax.envs import nanocraft as env
from php_jax.hierarchy import HierarchySpec

SPEC = HierarchySpec(
    name="nanocraft",
    levels=(("nanocraft",),
            ("moves_r", "moves_d", "builds_r", "builds_d", "builds_l", "builds_u"),
            ("move_r", "move_d", "build_r", "build_d", "build_l", "build_u")),
    action_sizes=env.ACTION_SIZES, obs_dim=env.OBS_DIM)


@struct.dataclass
class NanoCraftOracle:
  """Level-1 procedure p calls level-2 procedure p the needed number of times: x, y, w-1, h-1, w-1, h-1."""
  spec = SPEC

  def operation(self, level, proc, tau, obs, key):
    del key
    if level == 0:   # (moves_r, moves_d, builds_r, builds_d, builds_l, builds_u, return)
      return jnp.clip(tau, 0, 5)[None].astype(jnp.int32)
    if level == 1:
      return jnp.asarray(proc, jnp.int32)[None]
    direction = jnp.where(proc < 2, proc, proc - 2)  # move_r/d: RIGHT/DOWN; build_r/d/l/u: R/D/L/U
    action = jnp.where((proc >= 2) & (tau >= 1), env.PLACE_BLOCK, direction)
    return action[None].astype(jnp.int32)

  def terminates(self, level, proc, tau, obs, key):
    del key
    full, h, w, x, y = (obs[i].astype(jnp.int32) for i in range(5))
    if level == 0:
      return tau >= 5
    if level == 1:
      repeats = jnp.stack([x, y, w - 1, h - 1, w - 1, h - 1])[jnp.clip(proc, 0, 5)]
      return tau + 1 >= repeats
    return (proc < 2) | (tau >= 1) | (full == 1)
