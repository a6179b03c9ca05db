"""An expert's episodes in a Gymnasium environment, recorded as demonstration lines.

An expert is any object with `act(observation, info)` returning an action, or a pair `(action, stack)`
whose stack is the call stack that chose it (`[[procedure, counter], ...]`, root first, the demonstration
file's format, any sequences of ints, or None), and optionally `reset(observation, info)`, called at each
episode's start. The expert sees the environment's own observations (a dict stays a dict); the lines hold
them flattened. Episode i is reset with seed + i. `write_demonstrations` writes the lines as JSON lines or as
a binary set.
"""
from __future__ import annotations

import json
from collections.abc import Callable, Collection, Iterable, Iterator
from typing import Any

import gymnasium
import numpy as np

from php_jax.data import demo_files, files, shards
from php_jax.demos import UNKNOWN
from php_jax.envs import success
from php_jax.envs.gym.loading import max_steps_of
from php_jax.envs.gym.spaces import (GymError, action_factors, action_sizes, call_user_code, check_finite,
                                     check_observation_space, flatten_observation)
from php_jax.hierarchy import HierarchySpec


def _is_sequence(value) -> bool:
  return isinstance(value, (list, tuple, np.ndarray))


def _expert_output(output) -> tuple[Any, Any]:
  """(action, stack or None) from an expert's act(): a pair whose second item is None or a sequence of
  sequences (the frames) is (action, stack); anything else is a bare action."""
  if (isinstance(output, tuple) and len(output) == 2
      and (output[1] is None or (_is_sequence(output[1]) and all(_is_sequence(f) for f in output[1])))):
    return output
  return output, None


def _as_lists(value):
  """Sequences (lists, tuples, arrays) as lists, NumPy scalars as Python numbers, all the way down."""
  if _is_sequence(value):
    return [_as_lists(v) for v in value]
  return value.item() if isinstance(value, np.generic) else value


def _stack_spec(stacks: list, sizes: tuple[int, ...], episode: int) -> HierarchySpec:
  """A spec that admits every procedure id in an episode's stacks (for checking them without a hierarchy).
  Raises GymError naming the first step whose stack is not [[procedure, counter], ...] with as many levels as
  the first stack's."""
  given = [(t, frames) for t, frames in enumerate(stacks) if frames is not None]
  if not given:  # nothing to check
    return HierarchySpec("expert", (("p",), ("p",)), sizes, 0)
  first, depth = given[0][0], len(given[0][1])
  if depth < 2:
    raise GymError(f"episode {episode}, step {first}: the expert's stack {given[0][1]!r} has fewer than two "
                   "levels (a stack lists one [procedure, counter] pair per level, root first)")
  for t, frames in given:
    if len(frames) != depth:
      raise GymError(f"episode {episode}, step {t}: the expert's stack has {len(frames)} levels; at step {first} "
                     f"it had {depth} (one [procedure, counter] pair per level, root first, at every step)")
  widths = [1] * depth
  for t, frames in given:
    for level, frame in enumerate(frames[1:], 1):  # the root level has one procedure
      if isinstance(frame, list) and frame and isinstance(frame[0], int):
        if frame[0] >= demo_files.MAX_SIZE:
          raise GymError(f"episode {episode}, step {t}: the expert's procedure id {frame[0]} at level {level} is "
                         f"beyond {demo_files.MAX_SIZE - 1} (a hierarchy has at most {demo_files.MAX_SIZE} "
                         "procedures a level)")
        widths[level] = max(widths[level], frame[0] + 1)
  return HierarchySpec("expert", tuple(("p",) * w for w in widths), sizes, 0)


def record(env: gymnasium.Env, expert, episodes: int, seed: int, annotate: int | Collection[int] = 0,
           spec: HierarchySpec | None = None, on_episode: Callable[[success.Ending], None] | None = None
           ) -> list[dict]:
  """The expert's episodes as demonstration lines (dicts in the demonstration file's format): `recorded`'s
  lines, all of them."""
  return list(recorded(env, expert, episodes, seed, annotate, spec, on_episode))


def recorded(env: gymnasium.Env, expert, episodes: int, seed: int, annotate: int | Collection[int] = 0,
             spec: HierarchySpec | None = None, on_episode: Callable[[success.Ending], None] | None = None
             ) -> Iterator[dict]:
  """The expert's episodes as demonstration lines (dicts in the demonstration file's format), one at a time as
  each episode ends (`write_demonstrations` writes them as they come, holding one episode, or one shard).

  annotate: how many of the first episodes keep the stacks the expert gives, or which ones (their 0-based
  numbers, e.g. those `experiments.suggest` chose); the others are actions only. Every line is checked as the
  demonstration file reader checks it (against spec where given: procedure ids in range), so the stacks
  follow the call-stack rules. Raises GymError naming the episode and step of the first problem. An episode
  ends when the environment terminates or truncates it (wrap it in `gymnasium.wrappers.TimeLimit` for a step
  limit of your own), or, where it has no time limit, after DEFAULT_MAX_STEPS actions (then it counts as
  truncated). on_episode(ending) is
  called as each episode ends, with how it ended (`success.Ending`: for a progress display and for judging
  the expert's success).
  """
  on_episode = on_episode or (lambda _: None)
  check_observation_space(env.observation_space)
  sizes = action_sizes(env.action_space)
  limit = max_steps_of(env, None)
  keep = set(range(annotate) if isinstance(annotate, int) else annotate)
  for episode in range(episodes):
    line, stacks, ending = _episode(env, expert, seed + episode, limit, episode)
    if episode in keep:
      if all(s is None for s in stacks):
        raise GymError(f"episode {episode} is to be annotated, but the expert gave no call stack (its act() "
                       "returns a bare action, not (action, stack))")
      line["stack"] = stacks
    check = spec or _stack_spec(line.get("stack", []), sizes, episode)
    try:
      demo_files.parse_demonstration(line, check)
    except ValueError as e:
      raise GymError(f"episode {episode}: {e}") from None
    on_episode(ending)
    yield line


def _episode(env: gymnasium.Env, expert, seed: int, limit: int, episode: int
             ) -> tuple[dict, list, success.Ending]:
  """One episode of the expert, reset with seed: (its line without a stack, the stack it gave at each step
  (None where it gave none), how it ended). GymError naming the episode and step where the expert or the
  environment fails, or an observation is not finite."""
  observation_space, action_space = env.observation_space, env.action_space

  def where() -> str:
    return f"episode {episode}, step {len(actions)}"

  def flat(observation) -> list[float]:
    vector = flatten_observation(observation_space, observation)
    check_finite(vector, where())
    return vector.tolist()

  actions = []
  observation, info = call_user_code("the environment's reset()", where(), env.reset, seed=seed)
  if hasattr(expert, "reset"):
    call_user_code("the expert's reset()", where(), expert.reset, observation, info)
  observations, stacks = [flat(observation)], []
  rewards, terminated, truncated = [], False, False
  while not (terminated or truncated):
    step = where()
    action, stack = call_user_code("the expert's act()", step, lambda: _expert_output(expert.act(observation, info)))
    if not action_space.contains(action if not isinstance(action, list) else np.asarray(action)):
      raise GymError(f"{step}: the expert's action {action!r} is not in the action space {action_space}")
    actions.append(action_factors(action_space, action))
    stacks.append(None if stack is None else _as_lists(stack))
    observation, reward, terminated, truncated, info = call_user_code("the environment's step()", step, env.step,
                                                                      action)
    observations.append(flat(observation))
    rewards.append(float(reward))
    truncated = bool(truncated) or (len(actions) >= limit and not terminated)
  ending = success.Ending(sum(rewards), rewards[-1] if rewards else None, bool(terminated), truncated, dict(info))
  return {"observations": observations, "actions": actions}, stacks, ending


def write_demonstrations(path: str, lines: Iterable[dict], shard_size: int = shards.SHARD_SIZE) -> None:
  """Writes demonstration lines (`record`'s, or `recorded`'s as they come) to path whole or not at all: a binary
  set (`php_jax.data.shards`, shard_size demonstrations to a shard) where path ends in shards.SUFFIX, else JSON
  lines."""
  if shards.write_as_binary(path):
    shards.write_shards(path, _as_arrays(lines), shard_size)
  else:
    files.write_streamed(path, ((json.dumps(line) + "\n").encode() for line in lines))


def _as_arrays(lines: Iterable[dict]) -> Iterator[shards.Unpadded]:
  """lines as `_arrays`, each stack read at the depth of the first stack's first frame."""
  depth = None
  for line in lines:
    if depth is None:
      depth = next((len(frames) for frames in line.get("stack") or () if frames is not None), None)
    yield _arrays(line, depth)


def _arrays(line: dict, depth: int) -> shards.Unpadded:
  """One of `record`'s lines as arrays: observations [T+1, D] float32, actions [T, F] int32 and, where it
  carries a stack, its procedures and counters [T, depth] int32 (UNKNOWN where the expert gave none)."""
  stack, procs, taus = line.get("stack"), None, None
  if stack is not None:
    rows = [[[UNKNOWN, UNKNOWN] if f is None else f for f in frames or [None] * depth] for frames in stack]
    procs, taus = np.array(rows, np.int32).reshape(len(stack), depth, 2).transpose(2, 0, 1)
  return np.array(line["observations"], np.float32), np.array(line["actions"], np.int32), procs, taus
