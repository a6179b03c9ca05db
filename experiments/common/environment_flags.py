"""The flags of the commands that run a Gymnasium environment (`record`, `act`): which environment, the
episodes' seeds, their step limit and what counts as a success."""
from __future__ import annotations

from absl import flags

from php_jax.envs import gym, success
from php_jax.training.config import MAX_SEED

ENV = flags.DEFINE_string("env", None, "A registered Gymnasium id (Taxi-v3); module:EnvId, which imports module "
                          "(registering its environments) and makes EnvId (minigrid:BabyAI-GoToLocal-v0); or "
                          "module:attribute of a callable returning a gymnasium.Env.")
SEED = flags.DEFINE_integer("seed", 0, "Episode i is reset with seed + i.", lower_bound=0, upper_bound=MAX_SEED)
MAX_STEPS = flags.DEFINE_integer("max_steps", None, "Step limit per episode. Default: the environment's time "
                                 f"limit, else {gym.DEFAULT_MAX_STEPS}.", lower_bound=1)
SUCCESS = flags.DEFINE_string(
    "success", None, "What counts as a successful episode: info:KEY (the last step's info[KEY] is true), "
    "return>X or return>=X (the episode's return), reward>X or reward>=X (the last step's reward; BabyAI: "
    "reward>0), or terminated (it reached a terminal state of the environment, not just its time limit). Default: info:is_success where the "
    "environment reports it; otherwise success is unknown and not counted.")


def success_rule() -> success.SuccessRule | None:
  """--success parsed (None where not given); ValueError naming the flag's value otherwise."""
  return None if SUCCESS.value is None else success.parse(SUCCESS.value)
