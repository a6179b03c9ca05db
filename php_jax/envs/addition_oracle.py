"""The supervisor's hierarchy for long-hand addition (paper §5.2), as a Policy of pure functions of
(level, procedure, τ, observation): add → add1 → {write, carry, lshift} → elementary actions."""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from php_jax.envs import addition as env
from php_jax.hierarchy import HierarchySpec

SPEC = HierarchySpec(name="addition", levels=(("add",), ("add1",), ("write", "carry", "lshift")),
                     action_sizes=env.ACTION_SIZES, obs_dim=env.OBS_DIM)
WRITE_PROC, CARRY_PROC, LSHIFT_PROC = range(3)
# carry's three actions by τ: MOVE carry LEFT, WRITE carry 1, MOVE carry RIGHT.
_CARRY_ACTIONS = np.array([[env.MOVE, env.CARRY, env.LEFT], [env.WRITE, env.CARRY, 1],
                           [env.MOVE, env.CARRY, env.RIGHT]], np.int32)


def _column_sum(sym):
  digits = jnp.where(sym == env.EMPTY, 0, sym)
  return digits[env.IN1] + digits[env.IN2] + digits[env.CARRY]


@struct.dataclass
class AdditionOracle:
  """add calls add1 until in1, in2, carry read EMPTY; add1 = write, carry if the column sum ≥ 10, lshift."""
  spec = SPEC

  def operation(self, level, proc, tau, obs, key):
    del key
    sym = env.observed_symbols(obs)
    total = _column_sum(sym)
    if level == 0:
      return jnp.zeros(1, jnp.int32)
    if level == 1:
      callee = jnp.where(tau == 0, WRITE_PROC,
                         jnp.where((tau == 1) & (total >= 10), CARRY_PROC, LSHIFT_PROC))
      return callee[None].astype(jnp.int32)
    write = jnp.array([env.WRITE, env.OUT, 0], jnp.int32).at[2].set(total % 10)
    carry = jnp.asarray(_CARRY_ACTIONS)[jnp.clip(tau, 0, 2)]
    lshift = jnp.array([env.MOVE, 0, env.LEFT], jnp.int32).at[1].set(jnp.clip(tau, 0, 3))
    return jnp.stack([write, carry, lshift])[jnp.clip(proc, 0, 2)]

  def terminates(self, level, proc, tau, obs, key):
    del key
    sym = env.observed_symbols(obs)
    if level == 0:
      return jnp.all(sym[:3] == env.EMPTY)
    if level == 1:  # after lshift: at τ = 2, or at τ = 1 when no carry ran (the new column's out is EMPTY)
      return (tau == 2) | ((tau == 1) & (sym[env.OUT] == env.EMPTY))
    return jnp.stack([tau >= 0, tau == 2, tau == 3])[jnp.clip(proc, 0, 2)]
