"""Gymnasium spaces as php_jax's arrays: observations as float32 vectors (`gymnasium.spaces.flatten`: Discrete
one-hot, Box, MultiDiscrete and MultiBinary, and Dict and Tuple of these; a text, such as MiniGrid's mission,
as TEXT_WORDS word ids), with the fields that say what each number is (`observation_fields`, for the networks'
encoders); actions as factors (a `Discrete` action space is one factor, a `MultiDiscrete` one a factor per
entry). Any other space is refused with a `GymError` naming it."""
from __future__ import annotations

import re
import zlib

import gymnasium
import numpy as np
from gymnasium import spaces

from php_jax import encoders

TEXT_WORDS, TEXT_VOCAB = 32, 4096  # a text's words (at most), and the ids they are hashed to (0 pads)


class GymError(ValueError):
  """An environment, expert or policy that php_jax cannot use as given; the message says why."""


def call_user_code(what: str, where: str, function, *args, **kwargs):
  """function(*args, **kwargs): a call into the environment's or the expert's code, any exception it raises
  becoming a GymError in one line naming where it happened and what failed ("episode 3, step 7: the
  environment's step() failed: RuntimeError: ...")."""
  try:
    return function(*args, **kwargs)
  except GymError:
    raise
  except Exception as e:  # the user's code, failing in any way
    raise GymError(f"{where}: {what} failed: {type(e).__name__}: {e}") from None


def check_finite(observations: np.ndarray, where: str) -> None:
  """Raises GymError naming where unless every number of the flattened observation(s) is finite."""
  if not np.all(np.isfinite(observations)):
    raise GymError(f"{where}: the environment's observation holds NaN or infinity; php_jax needs finite numbers "
                   "(an observation wrapper can replace them)")


def check_observation_space(space: spaces.Space, where: str = "observation space") -> None:
  if isinstance(space, spaces.Dict):
    for key, sub in space.spaces.items():
      check_observation_space(sub, f"{where}[{key!r}]")
  elif isinstance(space, spaces.Tuple):
    for i, sub in enumerate(space.spaces):
      check_observation_space(sub, f"{where}[{i}]")
  elif not (_is_text(space) or isinstance(space, (spaces.Discrete, spaces.Box, spaces.MultiDiscrete,
                                                   spaces.MultiBinary))):
    raise GymError(f"the {where} {space} cannot be flattened to a vector (php_jax takes Discrete, Box, "
                   "MultiDiscrete, MultiBinary, Text, and Dict and Tuple of these)")


def _is_text(space: spaces.Space) -> bool:
  """Text, or MiniGrid's MissionSpace and its subclasses (spaces of strings that are not Text)."""
  return isinstance(space, spaces.Text) or any(c.__name__ == "MissionSpace" for c in type(space).__mro__)


def observation_fields(space: spaces.Space) -> tuple[encoders.Field, ...]:
  """What each number of the space's flattened observations is, in order (`php_jax.encoders`): Discrete →
  one unordered category, MultiDiscrete → an ordered category per entry (a row, a column; a hierarchy file's
  "observation" says otherwise), a Box of three axes with integer values → an image of codes 0..high, any
  other Box or a MultiBinary → numbers, a text → words."""
  check_observation_space(space)
  if isinstance(space, spaces.Dict):
    return tuple(f for sub in space.spaces.values() for f in observation_fields(sub))
  if isinstance(space, spaces.Tuple):
    return tuple(f for sub in space.spaces for f in observation_fields(sub))
  if _is_text(space):
    return (encoders.Tokens(TEXT_WORDS, TEXT_VOCAB),)
  if isinstance(space, spaces.Discrete):
    return (encoders.Categorical(int(space.n)),)
  if isinstance(space, spaces.MultiDiscrete):
    return tuple(encoders.Categorical(int(n), True) for n in np.ravel(space.nvec))
  if (isinstance(space, spaces.Box) and len(space.shape) == 3 and np.issubdtype(space.dtype, np.integer)
      and np.all(space.low >= 0) and np.all(space.high < 65536)):
    highs = np.asarray(space.high).reshape(-1, space.shape[2]).max(axis=0)
    return (encoders.Image(tuple(map(int, space.shape)), tuple(int(h) + 1 for h in highs)),)
  return (encoders.Real(int(spaces.flatdim(space))),)


def observation_size(space: spaces.Space) -> int:
  """The length of the space's observations as vectors."""
  return encoders.size(observation_fields(space))


def words(text: str, where: str = "text") -> np.ndarray:
  """A text as TEXT_WORDS word ids, float32: each word (lower case, letters and digits) hashed to
  1..TEXT_VOCAB−1, then zeros. GymError for a text of more words."""
  found = re.findall(r"[a-z0-9]+", text.lower())
  if len(found) > TEXT_WORDS:
    raise GymError(f"{where} has {len(found)} words; php_jax reads at most {TEXT_WORDS}: {text[:80]!r}")
  ids = [1 + zlib.crc32(w.encode()) % (TEXT_VOCAB - 1) for w in found]
  return np.asarray(ids + [0] * (TEXT_WORDS - len(ids)), np.float32)


def _check_observation(space: spaces.Space, observation, where: str = "observation") -> None:
  """Refuses an observation that space cannot flatten: a Discrete, MultiDiscrete or MultiBinary value the
  space does not contain, a Box value of another shape (values outside its bounds are taken), a Dict without
  one of its keys or a Tuple of another length, naming where."""
  if isinstance(space, spaces.Dict):
    if not (isinstance(observation, dict) and set(space.spaces) <= set(observation)):
      raise GymError(f"{where} must be a dict with the keys {sorted(space.spaces)}; got {observation!r}")
    for key, sub in space.spaces.items():
      _check_observation(sub, observation[key], f"{where}[{key!r}]")
  elif isinstance(space, spaces.Tuple):
    if not (isinstance(observation, (tuple, list)) and len(observation) == len(space.spaces)):
      raise GymError(f"{where} must be a tuple of {len(space.spaces)} values; got {observation!r}")
    for i, (sub, value) in enumerate(zip(space.spaces, observation)):
      _check_observation(sub, value, f"{where}[{i}]")
  elif _is_text(space):
    if not isinstance(observation, str):
      raise GymError(f"{where} must be a string; got {observation!r}")
    words(observation, where)
  elif isinstance(space, spaces.Box):
    if np.shape(observation) != space.shape:
      raise GymError(f"{where} must have the shape {space.shape} of {space}; got shape {np.shape(observation)}")
  elif not space.contains(np.asarray(observation) if isinstance(observation, list) else observation):
    raise GymError(f"{where} {observation!r} is not in {space}")


def flatten_observation(space: spaces.Space, observation) -> np.ndarray:
  """An observation of space as a float32 vector [observation_size(space)]. Raises GymError for an observation
  the space does not hold (Box values outside its bounds are taken)."""
  _check_observation(space, observation)
  return _flatten(space, observation)


def _flatten(space: spaces.Space, observation) -> np.ndarray:
  """As `gymnasium.spaces.flatten`, part by part (a Dict's in the order of its keys), a text as its words."""
  if isinstance(space, spaces.Dict):
    return np.concatenate([_flatten(sub, observation[key]) for key, sub in space.spaces.items()])
  if isinstance(space, spaces.Tuple):
    return np.concatenate([_flatten(sub, value) for sub, value in zip(space.spaces, observation)])
  if _is_text(space):
    return words(observation)
  return np.asarray(spaces.flatten(space, observation), np.float32)


def flatten_batch(envs: gymnasium.vector.VectorEnv, observations) -> np.ndarray:
  """A vector environment's observations as float32 vectors [M, observation_size], copy by copy as
  flatten_observation would, at once where the space allows."""
  space, num = envs.single_observation_space, envs.num_envs
  if isinstance(space, (spaces.Discrete, spaces.Box, spaces.MultiBinary)):
    # batch_space keeps these flattening alike, each copy's entries together
    return flatten_observation(envs.observation_space, observations).reshape(num, -1)
  if isinstance(space, spaces.MultiDiscrete):  # batched, a Box of the values: one-hot them here
    values = np.asarray(observations, np.int64).reshape(num, -1) - np.ravel(space.start)
    offsets = np.concatenate([[0], np.cumsum(np.ravel(space.nvec))[:-1]])
    flat = np.zeros((num, int(np.sum(space.nvec))), np.float32)
    flat[np.arange(num)[:, None], offsets + values] = 1
    return flat
  return np.stack([flatten_observation(space, o) for o in gymnasium.vector.utils.iterate(envs.observation_space,
                                                                                         observations)])


def action_sizes(space: spaces.Space) -> tuple[int, ...]:
  """The action factors' sizes: (n,) for Discrete(n), one per entry (row-major) for MultiDiscrete."""
  if isinstance(space, spaces.Discrete):
    return (int(space.n),)
  if isinstance(space, spaces.MultiDiscrete):
    return tuple(int(n) for n in np.ravel(space.nvec))
  raise GymError(f"the action space {space} is not Discrete or MultiDiscrete (php_jax's actions are factors "
                 "of finite sizes)")


def env_actions(space: spaces.Space, factors: np.ndarray) -> np.ndarray:
  """A vector environment's actions [M, ...] for M actions' factors [M, F] (int, each in its factor's range;
  GymError otherwise)."""
  sizes, given = action_sizes(space), np.asarray(factors)
  if given.ndim != 2 or given.shape[1] != len(sizes) or not np.issubdtype(given.dtype, np.integer):
    raise GymError(f"factors must be [M, {len(sizes)}] integers (one row per action); got {given.dtype} of shape "
                   f"{given.shape}")
  bad = np.argwhere((given < 0) | (given >= np.array(sizes)))
  if bad.size:
    m, f = bad[0]
    raise GymError(f"factors[{m}, {f}] = {given[m, f]} is outside 0..{sizes[f] - 1}")
  factors = given.astype(np.int64)
  if isinstance(space, spaces.Discrete):
    return int(space.start) + factors[:, 0]
  shape = (len(factors),) + space.nvec.shape
  return (np.ravel(space.start) + factors).reshape(shape).astype(space.dtype)


def action_factors(space: spaces.Space, action) -> list[int]:
  """An environment action's factors (int), each counted from 0. Raises GymError for an action the space does
  not contain."""
  action_sizes(space)  # refuses other spaces
  if not space.contains(np.asarray(action) if isinstance(action, list) else action):
    raise GymError(f"action {action!r} is not in the action space {space}")
  if isinstance(space, spaces.Discrete):
    return [int(action) - int(space.start)]
  return (np.ravel(np.asarray(action, np.int64)) - np.ravel(space.start)).tolist()
