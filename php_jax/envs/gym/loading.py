"""The environment and the expert a command names: a registered Gymnasium id, Gymnasium's module:EnvId, or
module:attribute of a callable; and an episode's step limit."""
from __future__ import annotations

from collections.abc import Callable
from typing import Any

import gymnasium

from php_jax.envs import import_path
from php_jax import encoders
from php_jax.envs.gym.spaces import GymError, call_user_code, observation_fields

DEFAULT_MAX_STEPS = 10_000  # an episode's step limit where the environment sets none


def _registered(name: str) -> Callable[[], gymnasium.Env]:
  try:
    gymnasium.spec(name)
  except gymnasium.error.Error as e:
    raise GymError(f"unknown environment {name!r}: {e}") from None
  return lambda: call_user_code("making it", f"environment {name!r}", gymnasium.make, name)


def env_maker(name: str) -> Callable[[], gymnasium.Env]:
  """A function making the environment `name`: a registered Gymnasium id ("Taxi-v3"); Gymnasium's
  "module:EnvId", which imports module (registering its environments) and makes EnvId
  ("minigrid:BabyAI-GoToLocal-v0"); or "module:attribute", a callable returning a gymnasium.Env. Raises
  GymError for an unknown id or an unloadable callable."""
  if ":" not in name:
    return _registered(name)
  module_name, _, attribute = name.partition(":")
  if module_name and attribute and not attribute.isidentifier():  # an id such as BabyAI-GoToLocal-v0
    import_path.load_module(module_name, "environment", GymError)
    return _registered(attribute)
  make = import_path.load_attribute(name, "environment", GymError)
  if not callable(make):
    raise GymError(f"environment {name!r} is a {type(make).__name__}, not a callable returning a gymnasium.Env")

  def checked() -> gymnasium.Env:
    try:
      env = make()
    except Exception as e:  # the user's code, failing in any way: one line naming it
      raise GymError(f"environment {name!r} failed: {type(e).__name__}: {e}") from None
    if not isinstance(env, gymnasium.Env):
      raise GymError(f"environment {name!r} returned a {type(env).__name__}, not a gymnasium.Env")
    return env

  return checked


def env_observation_fields(name: str) -> tuple[encoders.Field, ...]:
  """What each number of the named environment's flattened observations is (`spaces.observation_fields`), read
  from a copy of it made and closed."""
  env = env_maker(name)()
  try:
    return observation_fields(env.observation_space)
  finally:
    env.close()


def expert_maker(name: str) -> Callable[[gymnasium.Env], Any]:
  """The callable at "module:attribute" that takes the environment and returns an expert (GymError naming
  it if it fails, or returns something without act())."""
  make = import_path.load_attribute(name, "expert", GymError)
  if not callable(make):
    raise GymError(f"expert {name!r} is a {type(make).__name__}, not a callable taking the environment")

  def checked(env: gymnasium.Env) -> Any:
    try:
      expert = make(env)
    except Exception as e:  # the user's code, failing in any way: one line naming it
      raise GymError(f"expert {name!r} failed on this environment: {type(e).__name__}: {e}") from None
    if not callable(getattr(expert, "act", None)):
      raise GymError(f"expert {name!r} returned a {type(expert).__name__}, which has no act(observation, info)")
    return expert

  return checked


def max_steps_of(env: gymnasium.Env | gymnasium.vector.VectorEnv, max_steps: int | None) -> int:
  """An episode's step limit: max_steps where given, else the environment's time limit (a TimeLimit wrapper's,
  or its spec's; of a SyncVectorEnv, its first copy's), else DEFAULT_MAX_STEPS."""
  if max_steps is not None:
    return max_steps
  if isinstance(env, gymnasium.vector.SyncVectorEnv) and env.envs:
    env = env.envs[0]
  wrapped = env
  while isinstance(wrapped, gymnasium.Wrapper):
    if isinstance(wrapped, gymnasium.wrappers.TimeLimit):
      return wrapped._max_episode_steps
    wrapped = wrapped.env
  spec = getattr(env, "spec", None)
  return (spec.max_episode_steps if spec and spec.max_episode_steps else None) or DEFAULT_MAX_STEPS
