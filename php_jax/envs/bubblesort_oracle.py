"""The supervisor's hierarchy for bubble sort, as a Policy of pure functions of (level, procedure, τ,
observation): bubblesort → {bubble, reset} → {swapshift, shift, lshift, dece} → elementary actions.

bubblesort calls bubble when i = 0, else reset, and returns when i = 0 and j = e. bubble calls swapshift if
digit(i) > digit(j), else shift, and returns when j = e. reset calls dece first (j = e when it starts), then
lshift, and returns when i = 0. swapshift: SWAP, MOVE i RIGHT, MOVE j RIGHT; shift: MOVE i RIGHT, MOVE j RIGHT;
lshift: MOVE i LEFT, MOVE j LEFT; dece: MOVE e LEFT. reset's counter tells its first operation from the
others: after dece and one lshift, j = e holds again.
"""
from __future__ import annotations

import jax.numpy as jnp
import numpy as np
from flax import struct

from php_jax.envs import bubblesort as env
from php_jax.hierarchy import HierarchySpec

SPEC = HierarchySpec(name="bubblesort", levels=(("bubblesort",), ("bubble", "reset"),
                                                 ("swapshift", "shift", "lshift", "dece")),
                     action_sizes=env.ACTION_SIZES, obs_dim=env.OBS_DIM)
BUBBLE, RESET = range(2)
SWAPSHIFT, SHIFT, LSHIFT, DECE = range(4)
# [procedure, τ] → action; rows are padded with their last action.
_ACTIONS = np.array([
    [[env.SWAP, env.I, env.LEFT], [env.MOVE, env.I, env.RIGHT], [env.MOVE, env.J, env.RIGHT]],
    [[env.MOVE, env.I, env.RIGHT], [env.MOVE, env.J, env.RIGHT], [env.MOVE, env.J, env.RIGHT]],
    [[env.MOVE, env.I, env.LEFT], [env.MOVE, env.J, env.LEFT], [env.MOVE, env.J, env.LEFT]],
    [[env.MOVE, env.E, env.LEFT]] * 3], np.int32)
_LAST_TAU = np.array([2, 1, 1, 0], np.int32)


def _read(obs):
  """(digit under i, digit under j, i = 0, j = e) from an observation."""
  digit_i = jnp.argmax(obs[:env.NUM_SYMBOLS])
  digit_j = jnp.argmax(obs[env.NUM_SYMBOLS:2 * env.NUM_SYMBOLS])
  return digit_i, digit_j, obs[-2] > 0.5, obs[-1] > 0.5


@struct.dataclass
class BubbleSortOracle:
  spec = SPEC

  def operation(self, level, proc, tau, obs, key):
    del key
    digit_i, digit_j, i_at_start, j_at_end = _read(obs)
    if level == 0:
      callee = jnp.where(i_at_start, BUBBLE, RESET)
    elif level == 1:
      bubble = jnp.where(digit_i > digit_j, SWAPSHIFT, SHIFT)
      reset = jnp.where((tau == 0) & j_at_end, DECE, LSHIFT)
      callee = jnp.where(proc == BUBBLE, bubble, reset)
    else:
      return jnp.asarray(_ACTIONS)[jnp.clip(proc, 0, 3), jnp.clip(tau, 0, 2)]
    return callee[None].astype(jnp.int32)

  def terminates(self, level, proc, tau, obs, key):
    del key
    _, _, i_at_start, j_at_end = _read(obs)
    if level == 0:
      return i_at_start & j_at_end
    if level == 1:
      return jnp.where(proc == BUBBLE, j_at_end, i_at_start)
    return tau >= jnp.asarray(_LAST_TAU)[jnp.clip(proc, 0, 3)]
