"""The flags of the commands that run a Gymnasium environment (`record`, `act`): which environment, the
episodes' seeds and their step limit."""
from __future__ import annotations

from absl import flags

from php_jax.envs import gym

ENV = flags.DEFINE_string("env", None, "A registered Gymnasium id, or module:attribute of a callable returning a "
                          "gymnasium.Env.")
SEED = flags.DEFINE_integer("seed", 0, "Episode i is reset with seed + i.", lower_bound=0)
MAX_STEPS = flags.DEFINE_integer("max_steps", None, "Step limit per episode. Default: the environment's time "
                                 f"limit, else {gym.DEFAULT_MAX_STEPS}.", lower_bound=1)
