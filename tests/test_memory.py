"""A hierarchy's memory of the episode (`encoders.History`): its state depends on what was observed alone, the
E-step with it is exact (the lattice's inputs from training equal those the executor's step-by-step memory
gives, and the likelihood equals enumeration over every stack), it is saved and loaded, and an environment
that cannot be solved without remembering is learned end to end."""
from __future__ import annotations

import json

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from gymnasium import spaces

from php_jax.envs import gym
from php_jax.hierarchy import HierarchySpec
from php_jax.inference import stack_lattice
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint, objective
from php_jax.training.config import ConfigError, TrainConfig
from tests import processes
from tests.inference import lattice_brute_force as bf

SPEC = HierarchySpec("memory", (("root",), ("a", "b"), ("c", "d")), (2, 3), 4)
CAPACITY = (1, 3, 2)


def _hierarchy(seed: int = 0) -> PHPHierarchy:
  return PHPHierarchy(SPEC, hidden=(8,), memory=6, trunk=5, rngs=nnx.Rngs(seed))


def _demonstration(seed: int, num_steps: int = 4):
  rng = np.random.default_rng(seed)
  observations = jnp.asarray(rng.normal(size=(num_steps + 1, SPEC.obs_dim)), jnp.float32)
  actions = jnp.asarray(np.stack([rng.integers(n, size=num_steps) for n in SPEC.action_sizes], 1), jnp.int32)
  return observations, actions


def test_the_memory_reads_the_past_alone_and_changes_what_follows():
  hierarchy = _hierarchy()
  observations, actions = _demonstration(1, 6)
  level = hierarchy.levels[1]
  features = level.features(observations, actions)
  t = 3
  later = observations.at[t + 1:].add(1.0), actions.at[t:].set((actions[t:] + 1) % jnp.array(SPEC.action_sizes))
  changed = level.features(*later)
  np.testing.assert_array_equal(changed[:t + 1], features[:t + 1])  # o_0..o_t and a_0..a_{t−1} alone
  assert not np.allclose(changed[t + 1:, -6:], features[t + 1:, -6:])  # and the memory carries what it read


def _stepwise_inputs(hierarchy: PHPHierarchy, observations, actions) -> stack_lattice.StackInputs:
  """The lattice's inputs as the executor would meet them: the memory updated one observation at a time
  (`remember`), each decision's networks read through `step_features`."""
  num_steps, depth = actions.shape[0], SPEC.num_levels
  memory, per_step = hierarchy.initial_memory(), []
  for t in range(num_steps + 1):
    previous = actions[t - 1] if t else jnp.full(len(SPEC.action_sizes), -1, jnp.int32)
    memory = hierarchy.remember(memory, observations[t], previous)
    per_step.append([level.step_features(observations[t], memory[i]) for i, level in enumerate(hierarchy.levels)])
  log_call, log_stop, log_cont = [], [], []
  for i, level in enumerate(hierarchy.levels):
    tau = jnp.arange(CAPACITY[i], dtype=jnp.float32)
    now = jnp.concatenate([per_step[t][i] for t in range(num_steps)])
    after = jnp.concatenate([per_step[t + 1][i] for t in range(num_steps)])
    if i < depth - 1:
      log_call.append(level.op_log_probs(now, tau)[0])
    else:
      log_act = level.log_op(now, tau, actions)
    z = level.termination_logits(after, tau)
    log_stop.append(jax.nn.log_sigmoid(z))
    log_cont.append(jax.nn.log_sigmoid(-z))
  return stack_lattice.StackInputs(tuple(log_call), log_act, tuple(log_stop), tuple(log_cont), jnp.int32(num_steps))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_e_step_with_a_memory_is_exact(seed):
  hierarchy = _hierarchy(seed)
  observations, actions = _demonstration(seed + 10)
  trained = objective.stack_inputs(hierarchy, CAPACITY, observations, actions, jnp.int32(actions.shape[0]))
  stepwise = _stepwise_inputs(hierarchy, observations, actions)
  for got, want in zip(jax.tree.leaves(trained), jax.tree.leaves(stepwise)):
    np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-5)
  as_numpy = jax.tree.map(lambda x: np.asarray(x, np.float64), stepwise)
  log_z = bf.stack_posterior(as_numpy, actions.shape[0])[0]
  np.testing.assert_allclose(stack_lattice.log_likelihood(trained), log_z, rtol=1e-5)
  grads = nnx.grad(lambda h: stack_lattice.log_likelihood(
      objective.stack_inputs(h, CAPACITY, observations, actions, jnp.int32(actions.shape[0]))))(hierarchy)
  history_grads = jax.tree.leaves(nnx.state(grads, nnx.Param))
  assert all(np.isfinite(g).all() for g in history_grads)
  assert any(np.abs(g).sum() > 0 for g in jax.tree.leaves(grads.levels[2].history))


def test_a_hierarchy_with_a_memory_is_saved_loaded_and_trained_jointly_only(tmp_path):
  hierarchy = _hierarchy(3)
  checkpoint.save_hierarchy(str(tmp_path), "memory", hierarchy, (8,))
  assert json.loads((tmp_path / checkpoint.ARCHITECTURE_FILE).read_text())["memory"] == 6
  _, loaded = checkpoint.load_policy(str(tmp_path))
  observations, actions = _demonstration(4)
  want = objective.stack_inputs(hierarchy, CAPACITY, observations, actions, jnp.int32(4))
  got = objective.stack_inputs(loaded, CAPACITY, observations, actions, jnp.int32(4))
  for a, b in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
    np.testing.assert_array_equal(a, b)
  with pytest.raises(ConfigError, match="^memory: gru needs joint training"):
    TrainConfig(memory="gru", training="levelwise")


LENGTH = 6
LEFT, RIGHT = 0, 1
HIERARCHY = {"levels": [["root"], ["go_right", "go_back"]], "action_sizes": [2]}


class ThereAndBack(gymnasium.Env):
  """Walk to the corridor's right end and back to the cell you started from, seen as an image (the agent's
  cell has code 1): where to stop on the way back is seen only at the start, so it must be remembered."""

  observation_space = spaces.Box(0, 1, (1, LENGTH, 1), np.uint8)
  action_space = spaces.Discrete(2)

  def reset(self, *, seed=None, options=None):
    super().reset(seed=seed)
    self.start = self.position = int(self.np_random.integers(0, LENGTH - 1))
    self.been_right = False
    return self._observation(), {}

  def step(self, action):
    self.position = int(np.clip(self.position + (1 if action == RIGHT else -1), 0, LENGTH - 1))
    self.been_right |= self.position == LENGTH - 1
    done = self.been_right and self.position == self.start
    return self._observation(), -1.0, done, False, {"is_success": True} if done else {}

  def _observation(self):
    image = np.zeros((1, LENGTH, 1), np.uint8)
    image[0, self.position, 0] = 1
    return image


def make_there_and_back() -> gymnasium.Env:
  return gymnasium.wrappers.TimeLimit(ThereAndBack(), 4 * LENGTH)


class ThereAndBackExpert:
  """Root calls go_right to the end, then go_back to the start: [[0, τ_root], [procedure, steps so far]]."""

  def __init__(self, env):
    self.env = env

  def reset(self, observation, info):
    self.start, self.steps, self.back = int(np.argmax(observation[0, :, 0])), 0, False

  def act(self, observation, info):
    position = int(np.argmax(observation[0, :, 0]))
    if not self.back and position == LENGTH - 1:
      self.back, self.steps = True, 0
    self.steps += 1
    return (LEFT if self.back else RIGHT), [[0, int(self.back)], [int(self.back), self.steps - 1]]


@pytest.mark.parametrize("memory, solves", [("gru", True), ("none", False)])
def test_an_environment_that_needs_remembering_is_learned_with_a_memory_alone(tmp_path, memory, solves):
  lines = gym.record(make_there_and_back(), ThereAndBackExpert(None), episodes=30, seed=0, annotate=6)
  run = processes.fit_recorded(tmp_path, HIERARCHY, lines, "--env=tests.test_memory:make_there_and_back",
                               f"--memory={memory}", "--training=joint", "--episode_end=root",
                               "--iterations=100", "--eval_every=50",
                               "--hidden=32", "--learning_rate=0.01")
  _, policy = checkpoint.load_policy(str(run))
  assert policy.memory == (64 if memory == "gru" else None)
  episodes = gym.act(policy, gym.vector_env(make_there_and_back, 5), 25, seed=100)
  assert all(e["success"] for e in episodes) == solves, [e["steps"] for e in episodes]
