"""A learned policy (a PHP hierarchy or a flat baseline) acting in a Gymnasium environment, several copies of
it stepped together, each step's decisions one jitted call. Episode i is reset with seed + i."""
from __future__ import annotations

import functools
from collections.abc import Callable
from typing import NamedTuple

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx
from gymnasium import spaces

from php_jax import executor
from php_jax.envs import success
from php_jax.envs.gym.loading import max_steps_of
from php_jax.envs.gym.spaces import (GymError, action_sizes, call_user_code, check_finite, env_actions,
                                     flatten_batch, observation_size)
from php_jax.flat import FlatPolicy
from php_jax.model import PHPHierarchy


class _Stack(NamedTuple):
  """A hierarchy's memory per environment copy: the stack's procedures and counters [M, d], what the
  hierarchy remembers of the episode (`PHPHierarchy.remember`; () without a memory) and the last action
  [M, F]."""
  procedures: jax.Array
  counters: jax.Array
  remembered: tuple
  previous: jax.Array


class _Carry(NamedTuple):
  """A flat baseline's memory per copy: its cell's state (leaves [M, H]) and previous action [M, F]."""
  carry: tuple
  previous: jax.Array


def _hierarchy_decisions(policy: PHPHierarchy, memory: _Stack, obs, fresh, keys):
  """Per copy: a fresh episode's first stack, or the stack after the last action; and the next action."""
  spec = policy.spec

  def one(procs, taus, remembered, previous, o, is_fresh, key):
    stack_key, act_key = jax.random.split(key)
    remembered = jax.tree.map(lambda m, m0: jnp.where(is_fresh, m0, m), remembered, policy.initial_memory())
    remembered = policy.remember(remembered, o, jnp.where(is_fresh, -1, previous))
    recalled = policy.recall(remembered)
    started = executor.start_stack(recalled, spec, o, stack_key)
    after = executor.next_stack(recalled, spec, procs, taus, o, stack_key)
    procs, taus = (jnp.where(is_fresh, s, a) for s, a in zip(started, after[:2]))
    returned = ~is_fresh & after[2]
    action = executor.elementary_action(recalled, spec, procs, taus, o, act_key)
    return procs, taus, remembered, action, returned

  procs, taus, remembered, actions, returned = jax.vmap(one)(
      memory.procedures, memory.counters, memory.remembered, memory.previous, obs, fresh, keys)
  return _Stack(procs, taus, remembered, actions), actions, returned


def _flat_decisions(policy: FlatPolicy, memory: _Carry, obs, fresh, keys):
  """Per copy: the flat policy's step on obs (from its initial carry where fresh): stop, or the next action."""

  def one(carry, previous, o, is_fresh, key):
    carry = jax.tree.map(lambda c, c0: jnp.where(is_fresh, c0, c), carry, policy.initial_carry())
    previous = jnp.where(is_fresh, -1, previous)
    carry, factors, stop_logit = policy.step(carry, o, previous)
    action, stop = policy.decide(factors, stop_logit, key)
    return carry, action, stop

  carry, actions, stopped = jax.vmap(one)(memory.carry, memory.previous, obs, fresh, keys)
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
  keys = jax.vmap(lambda e, s: jax.random.fold_in(jax.random.fold_in(key, e), s))(episodes, steps)
  if isinstance(policy, FlatPolicy):
    return _flat_decisions(policy, memory, obs, fresh, keys)
  return _hierarchy_decisions(policy, memory, obs, fresh, keys)


def policy_sizes(policy: PHPHierarchy | FlatPolicy) -> tuple[int, tuple[int, ...]]:
  """(observation size, action factor sizes) a learned policy was trained with."""
  if isinstance(policy, PHPHierarchy):
    return policy.spec.obs_dim, policy.spec.action_sizes
  return policy.obs_dim, policy.action_sizes


def _initial_memory(policy, num: int):
  if isinstance(policy, PHPHierarchy):
    zeros = jnp.zeros((num, policy.spec.num_levels), jnp.int32)
    remembered = jax.tree.map(lambda x: jnp.zeros((num,) + x.shape, x.dtype), policy.initial_memory())
    return _Stack(zeros, zeros, remembered, jnp.full((num, len(policy.spec.action_sizes)), -1, jnp.int32))
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
    self.step_infos: dict = {}  # the vector environment's infos of its last step, every copy's
    self.reset_infos: list[dict] = [{} for _ in range(num_copies)]  # each copy's info at its episode's reset
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
                            bool(terminated), bool(truncated),
                            copy_info(self.step_infos, m) if steps else self.reset_infos[m])
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


def copy_info(infos: dict, m: int) -> dict:
  """Copy m's info out of a vector environment's infos: the entries it gave (arrays only: the entries
  Gymnasium batches per copy), read only when an episode ends."""
  info = {}
  for key, values in infos.items():
    given = infos.get(f"_{key}")  # Gymnasium's mask of the copies that gave the entry
    if key.startswith("_") or not isinstance(values, np.ndarray) or (given is not None and not given[m]):
      continue
    value = values[m]  # a NumPy scalar, an array, or (from an object array) any Python value
    info[key] = value.item() if isinstance(value, (np.generic, np.ndarray)) and np.ndim(value) == 0 else value
  return info


def act(policy: PHPHierarchy | FlatPolicy, env: gymnasium.Env | gymnasium.vector.VectorEnv, episodes: int,
        seed: int, max_steps: int | None = None, on_episode: Callable[[success.Ending], None] | None = None,
        success_rule: success.SuccessRule | None = None) -> list[dict]:
  """Runs a learned policy for `episodes` episodes in the real environment; episode i is reset with seed + i.

  A hierarchy runs by the executor's semantics: push the root and descend on the first observation; after each
  action pop the frames that stop, resume and descend. Either policy takes its most likely choices, or where
  policy.sample is set draws them (step t of episode i with a key folding in seed, i and t). The episode ends
  when the environment terminates or truncates it, when the policy stops (a hierarchy's root returns), or after
  max_steps actions (default: the environment's time limit, else DEFAULT_MAX_STEPS; then it counts as
  truncated). With a vector environment (`vector_env`) its copies run episodes side by side and each
  step's decisions are one jitted call over all copies.

  Returns per episode {"return", "steps", "success" (under success_rule; without one, info["is_success"] at
  the end where the environment reports it in any episode, else None: see `success`), "terminated",
  "truncated", "stack" (per step the call stack [[procedure, counter], ...], root first; None for a flat
  LSTM)}. on_episode(ending) is called as each episode ends, with how it ended (for a progress display).
  Raises ValueError if episodes < 1.
  """
  if episodes < 1:
    raise ValueError(f"episodes must be a positive integer; got {episodes}")
  on_episode = on_episode or (lambda _: None)
  envs = env if isinstance(env, gymnasium.vector.VectorEnv) else vector_env(lambda: env, 1)
  observation_space, action_space = envs.single_observation_space, envs.single_action_space
  check_policy(policy, observation_space, action_space)
  limit, num = max_steps_of(env, max_steps), envs.num_envs
  state = _Episodes(num, episodes, seed, isinstance(policy, PHPHierarchy))
  observations, infos = call_user_code("the environment's reset()", "acting", envs.reset,
                                       seed=state.assign(np.arange(num)))
  state.reset_infos = [copy_info(infos, m) for m in range(num)]
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
    observations, infos = call_user_code("the environment's reset()", "acting", envs.reset, seed=seeds,
                                         options={"reset_mask": mask})  # every copy's observation
    for m in copies:
      state.reset_infos[m] = copy_info(infos, m)
    fresh[copies] = True

  while (state.episode >= 0).any():
    while True:
      flat = flatten_batch(envs, observations)
      unfinite = np.flatnonzero(~np.isfinite(flat).all(axis=1) & (state.episode >= 0))
      if unfinite.size:
        m = unfinite[0]
        check_finite(flat[m], f"episode {state.episode[m]}, step {state.steps[m]}")
      new_memory, actions, returned = _decisions(
          (graphdef, treedef), leaves, memory, flat, fresh, (np.maximum(state.episode, 0), state.steps), key)
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
    observations, rewards, terminated, truncated, infos = call_user_code(
        "the environment's step()", "acting", envs.step, env_actions(action_space, actions))
    state.steps += 1
    state.returns += rewards
    state.last_rewards[:] = rewards
    state.step_infos = infos
    truncated = truncated | ((state.steps >= limit) & ~terminated)
    done = np.flatnonzero(terminated | truncated)
    for m in done:
      if state.episode[m] >= 0:
        on_episode(state.finish(m, bool(terminated[m]), bool(truncated[m])))
    if done.size:
      restart(done)
  return state.judged(success_rule)
