"""Any Gymnasium environment as a php_jax world: observations as vectors, actions as factors, an expert's
episodes recorded as demonstrations, and a learned policy acting in the real environment.

Observations are `gymnasium.spaces.flatten`ed to float32 vectors (Discrete one-hot, Box, MultiDiscrete and
MultiBinary, and Dict and Tuple of these). A `Discrete` action space is one action factor; a
`MultiDiscrete` one is a factor per entry. Any other space is refused with a `GymError` naming it.

An expert is any object with `act(observation, info)` returning an action, or a pair `(action, stack)`
whose stack is the call stack that chose it (`[[procedure, counter], ...]`, root first, the demonstration
file's format, any sequences of ints, or None), and optionally `reset(observation, info)`, called at each
episode's start. The expert sees the environment's own observations (a dict stays a dict); the files hold
them flattened. Episode i is reset with seed + i, in `record` and in `act` alike.
"""
from __future__ import annotations

import functools
from collections.abc import Callable, Collection
from typing import Any, NamedTuple

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from gymnasium import spaces

from php_jax import executor
from php_jax.data import demo_files
from php_jax.envs import import_path, success
from php_jax.flat_lstm import FlatLSTMPolicy
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy

DEFAULT_MAX_STEPS = 10_000  # an episode's step limit where the environment sets none


class GymError(ValueError):
  """An environment, expert or policy that php_jax cannot use as given; the message says why."""


def _check_observation_space(space: spaces.Space, where: str = "observation space") -> None:
  if isinstance(space, spaces.Dict):
    for key, sub in space.spaces.items():
      _check_observation_space(sub, f"{where}[{key!r}]")
  elif isinstance(space, spaces.Tuple):
    for i, sub in enumerate(space.spaces):
      _check_observation_space(sub, f"{where}[{i}]")
  elif not isinstance(space, (spaces.Discrete, spaces.Box, spaces.MultiDiscrete, spaces.MultiBinary)):
    raise GymError(f"the {where} {space} cannot be flattened to a vector (php_jax takes Discrete, Box, "
                   "MultiDiscrete, MultiBinary, and Dict and Tuple of these)")


def observation_size(space: spaces.Space) -> int:
  """The length of the space's observations as vectors."""
  _check_observation_space(space)
  return int(spaces.flatdim(space))


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
  elif isinstance(space, spaces.Box):
    if np.shape(observation) != space.shape:
      raise GymError(f"{where} must have the shape {space.shape} of {space}; got shape {np.shape(observation)}")
  elif not space.contains(np.asarray(observation) if isinstance(observation, list) else observation):
    raise GymError(f"{where} {observation!r} is not in {space}")


def flatten_observation(space: spaces.Space, observation) -> np.ndarray:
  """An observation of space as a float32 vector [observation_size(space)]. Raises GymError for an observation
  the space does not hold (Box values outside its bounds are taken)."""
  _check_observation(space, observation)
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


def _registered(name: str) -> Callable[[], gymnasium.Env]:
  try:
    gymnasium.spec(name)
  except gymnasium.error.Error as e:
    raise GymError(f"unknown environment {name!r}: {e}") from None
  return lambda: gymnasium.make(name)


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


def _max_steps(env: gymnasium.Env | gymnasium.vector.VectorEnv, max_steps: int | None) -> int:
  if max_steps is not None:
    return max_steps
  spec = getattr(env, "spec", None)
  return (spec.max_episode_steps if spec and spec.max_episode_steps else None) or DEFAULT_MAX_STEPS


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
  for t, frames in given:
    if depth < 2:
      raise GymError(f"episode {episode}, step {t}: the expert's stack {frames!r} has fewer than two levels (a "
                     "stack lists one [procedure, counter] pair per level, root first)")
    if len(frames) != depth:
      raise GymError(f"episode {episode}, step {t}: the expert's stack has {len(frames)} levels; at step {first} "
                     f"it had {depth} (one [procedure, counter] pair per level, root first, at every step)")
  widths = [1] * depth
  for _, frames in given:
    for level, frame in enumerate(frames[1:], 1):  # the root level has one procedure
      if isinstance(frame, list) and frame and isinstance(frame[0], int):
        widths[level] = max(widths[level], frame[0] + 1)
  return HierarchySpec("expert", tuple(("p",) * w for w in widths), sizes, 0)


def record(env: gymnasium.Env, expert, episodes: int, seed: int, annotated: int = 0,
           spec: HierarchySpec | None = None, max_steps: int | None = None,
           on_episode: Callable[[success.Ending], None] | None = None,
           annotate: Collection[int] | None = None) -> list[dict]:
  """The expert's episodes as demonstration lines (dicts in the demonstration file's format).

  The first `annotated` episodes keep the stacks the expert gives (or, where given, the episodes whose
  0-based numbers `annotate` holds, e.g. those `experiments.suggest` chose); the others are actions only.
  Every line is checked as the demonstration file reader checks it (against spec where given: procedure ids in range),
  so the stacks follow the call-stack rules. Raises GymError naming the episode and step of the first
  problem. An episode ends when the environment terminates or truncates it, or after max_steps actions
  (default: the environment's time limit, else DEFAULT_MAX_STEPS; then it counts as truncated).
  on_episode(ending) is called as each episode ends, with how it ended (`success.Ending`: for a progress
  display and for judging the expert's success).
  """
  on_episode = on_episode or (lambda _: None)
  observation_space, action_space = env.observation_space, env.action_space
  _check_observation_space(observation_space)
  sizes = action_sizes(action_space)
  limit = _max_steps(env, max_steps)
  keep = set(range(annotated) if annotate is None else annotate)
  lines = []
  for episode in range(episodes):
    observation, info = env.reset(seed=seed + episode)
    if hasattr(expert, "reset"):
      expert.reset(observation, info)
    observations, actions, stacks = [flatten_observation(observation_space, observation).tolist()], [], []
    rewards, terminated, truncated = [], False, False
    while not (terminated or truncated):
      try:
        action, stack = _expert_output(expert.act(observation, info))
      except Exception as e:  # the user's code, failing in any way: one line naming where
        raise GymError(f"episode {episode}, step {len(actions)}: the expert's act() failed: "
                       f"{type(e).__name__}: {e}") from None
      if not action_space.contains(action if not isinstance(action, list) else np.asarray(action)):
        raise GymError(f"episode {episode}, step {len(actions)}: the expert's action {action!r} is not in the "
                       f"action space {action_space}")
      actions.append(action_factors(action_space, action))
      stacks.append(None if stack is None else _as_lists(stack))
      observation, reward, terminated, truncated, info = env.step(action)
      observations.append(flatten_observation(observation_space, observation).tolist())
      rewards.append(float(reward))
      truncated = bool(truncated) or (len(actions) >= limit and not terminated)
    line = {"observations": observations, "actions": actions}
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
    lines.append(line)
    on_episode(success.Ending(sum(rewards), rewards[-1] if rewards else None, bool(terminated), truncated,
                              dict(info)))
  return lines


class _Stack(NamedTuple):
  """A hierarchy's memory per environment copy: the stack's procedures and counters [M, d]."""
  procedures: jax.Array
  counters: jax.Array


class _Carry(NamedTuple):
  """The flat LSTM's memory per copy: its carry ([M, H] twice) and previous action [M, F]."""
  carry: tuple
  previous: jax.Array


def _hierarchy_decisions(policy: PHPHierarchy, memory: _Stack, obs, fresh, keys):
  """Per copy: a fresh episode's first stack, or the stack after the last action; and the next action."""
  spec = policy.spec

  def one(procs, taus, o, is_fresh, key):
    stack_key, act_key = jax.random.split(key)
    started = executor.start_stack(policy, spec, o, stack_key)
    after = executor.next_stack(policy, spec, procs, taus, o, stack_key)
    procs, taus = (jnp.where(is_fresh, s, a) for s, a in zip(started, after[:2]))
    returned = ~is_fresh & after[2]
    return procs, taus, executor.elementary_action(policy, spec, procs, taus, o, act_key), returned

  procs, taus, actions, returned = jax.vmap(one)(memory.procedures, memory.counters, obs, fresh, keys)
  return _Stack(procs, taus), actions, returned


def _lstm_decisions(policy: FlatLSTMPolicy, memory: _Carry, obs, fresh):
  """Per copy: the LSTM's step on obs (from its initial carry where fresh): stop, or the next action."""

  def one(carry, previous, o, is_fresh):
    carry = jax.tree.map(lambda c, c0: jnp.where(is_fresh, c0, c), carry, policy.initial_carry(o.dtype))
    previous = jnp.where(is_fresh, -1, previous)
    carry, factors, stop = policy.step(carry, o, previous)
    action = jnp.stack([jnp.argmax(lp) for lp in factors]).astype(jnp.int32)
    return carry, action, stop > 0

  carry, actions, stopped = jax.vmap(one)(memory.carry, memory.previous, obs, fresh)
  return _Carry(carry, actions), actions, stopped


@functools.partial(jax.jit, static_argnames="structure")
def _decisions(structure: tuple, leaves: list, memory, obs, fresh, clock: tuple, key):
  """One step's decisions for every copy [M]: (memory, actions [M, F], episode ended by the policy [M]).
  The policy arrives split (structure: `nnx.split`'s graphdef and its state's treedef; leaves: the state's
  arrays) so that calls pass arrays, not a module; clock: (episode [M], step [M]), which the PRNG key of copy m
  folds in."""
  graphdef, treedef = structure
  episodes, steps = clock
  policy = nnx.merge(graphdef, jax.tree.unflatten(treedef, leaves))
  if isinstance(policy, FlatLSTMPolicy):
    return _lstm_decisions(policy, memory, obs, fresh)
  keys = jax.vmap(lambda e, s: jax.random.fold_in(jax.random.fold_in(key, e), s))(episodes, steps)
  return _hierarchy_decisions(policy, memory, obs, fresh, keys)


def policy_sizes(policy: PHPHierarchy | FlatLSTMPolicy) -> tuple[int, tuple[int, ...]]:
  """(observation size, action factor sizes) a learned policy was trained with."""
  if isinstance(policy, PHPHierarchy):
    return policy.spec.obs_dim, policy.spec.action_sizes
  return policy.cell.in_features - sum(policy.action_sizes), policy.action_sizes


def _initial_memory(policy, num: int):
  if isinstance(policy, PHPHierarchy):
    zeros = jnp.zeros((num, policy.spec.num_levels), jnp.int32)
    return _Stack(zeros, zeros)
  carry = jax.tree.map(lambda x: jnp.zeros((num,) + x.shape, x.dtype), policy.initial_carry())
  return _Carry(carry, jnp.full((num, len(policy.action_sizes)), -1, jnp.int32))


def check_policy(policy, observation_space: spaces.Space, action_space: spaces.Space) -> None:
  """Raises GymError unless the policy's observation and action sizes are the environment's."""
  obs_dim, sizes = policy_sizes(policy)
  if observation_size(observation_space) != obs_dim:
    raise GymError(f"the policy observes vectors of {obs_dim} numbers; this environment's observations "
                   f"flatten to {observation_size(observation_space)} ({observation_space})")
  if action_sizes(action_space) != tuple(sizes):
    raise GymError(f"the policy's actions have factor sizes {list(sizes)}; this environment's "
                   f"{action_space} has {list(action_sizes(action_space))}")


def vector_env(make_env: Callable[[], gymnasium.Env], num_envs: int) -> gymnasium.vector.VectorEnv:
  """num_envs copies of make_env() stepped together, reset only when `act` says (no autoreset)."""
  return gymnasium.vector.SyncVectorEnv([make_env] * num_envs,
                                        autoreset_mode=gymnasium.vector.AutoresetMode.DISABLED)


class _Episodes:
  """The host side of `act`: which episode each copy runs, and what each episode has done so far."""

  def __init__(self, num_copies: int, episodes: int, seed: int, with_stacks: bool):
    self.seed, self.total, self.next = seed, episodes, 0
    self.episode = np.full(num_copies, -1)    # the episode each copy runs; −1: idle
    self.steps = np.zeros(num_copies, np.int64)
    self.returns = np.zeros(num_copies)
    self.last_rewards = np.zeros(num_copies)
    self.infos: list[dict] = [{} for _ in range(num_copies)]  # each copy's info of its last step or reset
    self.stacks = [[] for _ in range(num_copies)] if with_stacks else None
    self.results: list[dict | None] = [None] * episodes
    self.endings: list[success.Ending | None] = [None] * episodes

  def assign(self, copies: np.ndarray) -> list[int | None]:
    """Starts the next episodes on copies; returns each copy's reset seed (None for copies left idle)."""
    seeds = []
    for m in copies:
      if self.next < self.total:
        self.episode[m], self.next = self.next, self.next + 1
        seeds.append(self.seed + int(self.episode[m]))
      else:
        self.episode[m] = -1
        seeds.append(None)
      self.steps[m], self.returns[m], self.last_rewards[m] = 0, 0.0, 0.0
      if self.stacks is not None:
        self.stacks[m] = []
    return seeds

  def finish(self, m: int, terminated: bool, truncated: bool) -> success.Ending:
    """Ends copy m's episode; returns how it ended."""
    steps = int(self.steps[m])
    ending = success.Ending(float(self.returns[m]), float(self.last_rewards[m]) if steps else None,
                            bool(terminated), bool(truncated), self.infos[m])
    self.endings[self.episode[m]] = ending
    self.results[self.episode[m]] = {
        "return": ending.episode_return, "steps": steps, "success": None, "terminated": ending.terminated,
        "truncated": ending.truncated, "stack": self.stacks[m] if self.stacks is not None else None}
    self.episode[m] = -1
    return ending

  def judged(self, rule: success.SuccessRule | None) -> list[dict]:
    """The episodes' results, each with its success under rule (`success.judge_all`)."""
    _, successes = success.judge_all(rule, self.endings)
    for result, succeeded in zip(self.results, successes):
      result["success"] = succeeded
    return self.results


def _copy_infos(infos: dict, num: int) -> list[dict]:
  """A vector environment's infos as one dict per copy, each with the entries that copy gave (arrays only:
  the entries Gymnasium batches per copy)."""
  per_copy = [{} for _ in range(num)]
  for key, values in infos.items():
    if key.startswith("_") or not isinstance(values, np.ndarray):
      continue
    given = infos.get(f"_{key}", np.ones(num, bool))
    for m in np.flatnonzero(given):
      per_copy[m][key] = values[m].item() if values[m].ndim == 0 else values[m]
  return per_copy


def act(policy: PHPHierarchy | FlatLSTMPolicy, env: gymnasium.Env | gymnasium.vector.VectorEnv, episodes: int,
        seed: int, max_steps: int | None = None, on_episode: Callable[[success.Ending], None] | None = None,
        success_rule: success.SuccessRule | None = None) -> list[dict]:
  """Runs a learned policy for `episodes` episodes in the real environment; episode i is reset with seed + i.

  A hierarchy runs by the executor's semantics (greedy, or sampling when built with sample=True): push the
  root and descend on the first observation; after each action pop the frames that stop, resume and descend;
  the episode ends when the environment terminates or truncates it, when the root returns, or after
  max_steps actions (default: the environment's time limit, else DEFAULT_MAX_STEPS; then it counts as
  truncated). With a vector environment (`vector_env`) its copies run episodes side by side and each
  step's decisions are one jitted call over all copies.

  Returns per episode {"return", "steps", "success" (under success_rule; without one, info["is_success"] at
  the end where the environment reports it in any episode, else None: see `success`), "terminated",
  "truncated", "stack" (per step the call stack [[procedure, counter], ...], root first; None for a flat
  LSTM)}. on_episode(ending) is called as each episode ends, with how it ended (for a progress display).
  """
  on_episode = on_episode or (lambda _: None)
  envs = env if isinstance(env, gymnasium.vector.VectorEnv) else vector_env(lambda: env, 1)
  observation_space, action_space = envs.single_observation_space, envs.single_action_space
  check_policy(policy, observation_space, action_space)
  limit, num = _max_steps(env, max_steps), envs.num_envs
  state = _Episodes(num, episodes, seed, isinstance(policy, PHPHierarchy))
  observations, infos = envs.reset(seed=state.assign(np.arange(num)))
  state.infos = _copy_infos(infos, num)
  memory, fresh, key = _initial_memory(policy, num), np.ones(num, bool), jax.random.key(seed)
  graphdef, params = nnx.split(policy)
  leaves, treedef = jax.tree.flatten(params)

  def restart(copies: np.ndarray) -> None:
    nonlocal observations
    mask = np.zeros(num, bool)
    mask[copies] = True
    seeds = [None] * num
    for m, s in zip(copies, state.assign(copies)):
      seeds[m] = s
    observations, infos = envs.reset(seed=seeds, options={"reset_mask": mask})  # every copy's observation
    reset_infos = _copy_infos(infos, num)
    for m in copies:
      state.infos[m] = reset_infos[m]
    fresh[copies] = True

  while (state.episode >= 0).any():
    while True:
      new_memory, actions, returned = _decisions(
          (graphdef, treedef), leaves, memory, flatten_batch(envs, observations), fresh,
          (np.maximum(state.episode, 0), state.steps), key)
      ended = np.flatnonzero(np.asarray(returned) & (state.episode >= 0))
      if not ended.size:
        break
      for m in ended:  # the policy ended the episode before the environment did
        on_episode(state.finish(m, False, False))
      restart(ended)
    memory, fresh = new_memory, np.zeros(num, bool)
    actions = np.asarray(actions)
    if state.stacks is not None:
      frames = np.stack([np.asarray(memory.procedures), np.asarray(memory.counters)], -1).tolist()  # [M][d][2]
      for m in np.flatnonzero(state.episode >= 0):
        state.stacks[m].append(frames[m])
    observations, rewards, terminated, truncated, infos = envs.step(env_actions(action_space, actions))
    state.steps += 1
    state.returns += rewards
    state.last_rewards[:] = rewards
    state.infos = _copy_infos(infos, num)
    truncated = truncated | ((state.steps >= limit) & ~terminated)
    done = np.flatnonzero(terminated | truncated)
    for m in done:
      if state.episode[m] >= 0:
        on_episode(state.finish(m, bool(terminated[m]), bool(truncated[m])))
    if done.size:
      restart(done)
  return state.judged(success_rule)
