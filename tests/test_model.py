"""PHP networks: the split first layer equals a plain MLP on concat(obs, τ), the factorized head is a
distribution, the τ switch, the LSTM root is causal, and random hierarchies run without retracing."""
import dataclasses

import chex
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax import executor
from php_jax.envs import addition, tasks
from php_jax.model import PHPHierarchy, PHPLevel, RootLSTM, RootMLP


def _plain_mlp(mlps, proc, obs, tau):
  x = jnp.concatenate([obs, jnp.array([tau])])
  kernels, biases = list(mlps.kernels), list(mlps.biases)
  for i, (k, b) in enumerate(zip(kernels, biases)):
    x = x @ k[...][proc] + b[...][proc]
    if i < len(kernels) - 1:
      x = jax.nn.relu(x)
  return x


def test_split_first_layer_equals_plain_mlp_on_concatenated_input():
  level = PHPLevel(3, 44, (2, 4, 10), hidden=(16, 8), rngs=nnx.Rngs(0))
  obs = jax.random.normal(jax.random.key(1), (5, 44))
  tau = jnp.arange(4.0)
  grid = level.operation(obs, tau)
  assert grid.shape == (3, 16, 5, 4)
  for n, k, m in [(0, 0, 0), (4, 2, 3), (2, 1, 1)]:
    np.testing.assert_allclose(grid[k, :, n, m], _plain_mlp(level.operation, k, obs[n], tau[m]), atol=1e-5)


def test_factorized_head_is_a_distribution_over_all_actions():
  level = PHPLevel(2, 44, (2, 4, 10), rngs=nnx.Rngs(0))
  obs = jax.random.normal(jax.random.key(2), (1, 44))
  actions = jnp.array([[k, t, a] for k in range(2) for t in range(4) for a in range(10)])
  log_probs = level.log_op(jnp.repeat(obs, len(actions), axis=0), jnp.array([1.0]), actions)[:, :, 0]
  np.testing.assert_allclose(jnp.exp(log_probs).sum(axis=0), 1.0, atol=1e-5)


def test_termination_ignores_tau_when_switched_off():
  obs = jax.random.normal(jax.random.key(3), (2, 5))
  tau = jnp.arange(6.0)
  hidden = PHPLevel(2, 5, (5,), tau_in_termination=False, rngs=nnx.Rngs(0)).termination_logits(obs, tau)
  seen = PHPLevel(2, 5, (5,), tau_in_termination=True, rngs=nnx.Rngs(0)).termination_logits(obs, tau)
  np.testing.assert_allclose(hidden, hidden[:, :, :1] * jnp.ones((1, 1, 6)), atol=1e-6)
  assert not np.allclose(seen[:, :, 0], seen[:, :, 5])


def test_tau_limit_makes_counters_past_it_look_alike():
  level = PHPLevel(3, 5, (4, 2), hidden=(8,), tau_limit=1, rngs=nnx.Rngs(0))
  obs, tau = jax.random.normal(jax.random.key(1), (4, 5)), jnp.arange(6.0)
  ops = jnp.array([[0, 1], [3, 0], [2, 1], [1, 1]])
  for out in (level.log_op(obs, tau, ops), level.termination_logits(obs, tau),
              level.op_log_probs(obs, tau)[0]):
    for t in range(2, 6):
      np.testing.assert_allclose(out[:, :, t], out[:, :, 1], atol=1e-6)
    assert not np.allclose(out[:, :, 0], out[:, :, 1])
  unlimited = PHPLevel(3, 5, (4, 2), hidden=(8,), rngs=nnx.Rngs(0))
  np.testing.assert_array_equal(unlimited.log_op(obs, tau[:2], ops), level.log_op(obs, tau[:2], ops))


def test_a_procedure_sees_only_the_observation_entries_it_observes():
  """State abstraction: procedure 0 observes entries 0 and 2, procedure 1 none, procedure 2 all; what a
  procedure does not observe changes neither its outputs nor, through them, any gradient."""
  level = PHPLevel(3, 5, (4,), hidden=(8,), observes=((0, 2), (), None), rngs=nnx.Rngs(0))
  obs, tau = jax.random.normal(jax.random.key(1), (4, 5)), jnp.arange(3.0)
  changed = obs.at[:, jnp.array([1, 3, 4])].set(9.0)
  for out in (lambda o: level.termination_logits(o, tau), lambda o: level.op_log_probs(o, tau)[0]):
    np.testing.assert_allclose(out(changed)[:, :2], out(obs)[:, :2], atol=1e-6)
    assert not np.allclose(out(changed)[:, 2], out(obs)[:, 2])
  empty = PHPLevel(3, 5, (4,), hidden=(8,), observes=((), (), ()), rngs=nnx.Rngs(0))
  np.testing.assert_allclose(empty.termination_logits(obs, tau), empty.termination_logits(changed * 2, tau),
                             atol=1e-6)
  spec = tasks.get("nanocraft").spec
  observes = (None, None, tuple((0,) for _ in spec.levels[2]))
  hierarchy = PHPHierarchy(dataclasses.replace(spec, observes=observes), hidden=(8,), rngs=nnx.Rngs(0))
  assert hierarchy.levels[2].observes == observes[2] and hierarchy.levels[1].observes is None
  with pytest.raises(ValueError, match="names observation entry 99, outside"):
    dataclasses.replace(spec, observes=(None, None, tuple((99,) for _ in spec.levels[2])))
  with pytest.raises(ValueError, match="observes must give one entry per level"):
    PHPHierarchy(dataclasses.replace(spec, observes=(None,)), rngs=nnx.Rngs(0))


def test_root_networks_give_distributions_and_lstm_is_causal():
  obs = jax.random.normal(jax.random.key(4), (7, 44))
  for root in (RootMLP(44, 3, rngs=nnx.Rngs(0)), RootLSTM(44, 3, rngs=nnx.Rngs(0))):
    out = root(obs)
    assert out.shape == (7, 3)
    np.testing.assert_allclose(jnp.exp(out).sum(-1), 1.0, atol=1e-5)
  lstm = RootLSTM(44, 3, rngs=nnx.Rngs(0))
  changed = obs.at[4:].set(0.0)
  np.testing.assert_allclose(lstm(obs)[:4], lstm(changed)[:4], atol=1e-6)
  assert not np.allclose(lstm(obs)[4:], lstm(changed)[4:])


def test_random_php_hierarchies_run_in_the_executor_without_retracing():
  task = tasks.get("addition")
  traced = jax.jit(chex.assert_max_traces(executor.rollout_batch, n=1),
                   static_argnames=("spec", "env", "max_steps", "record"))
  keys = jax.random.split(jax.random.key(0), 8)
  for seed in range(3):
    model = PHPHierarchy(task.spec, hidden=(32,), rngs=nnx.Rngs(seed))
    states = jax.vmap(lambda k: addition.sample_problem(k, 4, 8))(jax.random.split(jax.random.key(seed), 8))
    out = traced(model, task.spec, addition, states, keys, 40)
    assert out.actions.shape == (8, 40, 3)
    lengths = np.asarray(out.length)
    assert np.all((lengths >= 1) & (lengths <= 40))
    # A run stops early only because the root returned or an action was invalid.
    assert np.all((lengths == 40) | np.asarray(out.terminated) | ~np.asarray(out.valid))


def test_sampling_hierarchy_draws_valid_operations():
  task = tasks.get("nanocraft")
  model = PHPHierarchy(task.spec, sample=True, rngs=nnx.Rngs(0))
  obs = jnp.array([0.0, 2, 3, 1, 1])
  keys = jax.random.split(jax.random.key(0), 30)

  def draws(m):
    return set(np.asarray(jax.jit(jax.vmap(
        lambda k: m.operation(1, jnp.int32(2), jnp.int32(0), obs, k)[0]))(keys)).tolist())

  ops = draws(model)
  assert ops <= set(range(6)) and len(ops) > 1
  assert len(draws(PHPHierarchy(task.spec, rngs=nnx.Rngs(0)))) == 1


def test_a_trunk_is_one_encoding_every_procedure_and_counter_reads():
  """With a trunk, each network is the plain MLP on concat(relu(W o + b), τ): the encoding computed once and
  shared by every procedure, for both heads; a model saved with one loads with it and acts alike."""
  level = PHPLevel(3, 44, (2, 4), hidden=(8,), trunk=6, rngs=nnx.Rngs(0))
  obs, tau = jax.random.normal(jax.random.key(1), (5, 44)), jnp.arange(3.0)
  features = level.encode(obs)
  assert features.shape == (5, 6) and bool(jnp.all(features >= 0))
  np.testing.assert_allclose(features, jax.nn.relu(obs @ level.trunk.layer.kernel[...] + level.trunk.layer.bias[...]),
                             atol=1e-5)
  grid = level.operation(features, tau)
  for n, k, m in [(0, 0, 0), (4, 2, 2)]:
    np.testing.assert_allclose(grid[k, :, n, m], _plain_mlp(level.operation, k, features[n], tau[m]), atol=1e-5)
  assert level.operation.kernels[0][...].shape == (3, 7, 8)  # the trunk's width and τ, not the observation
  with pytest.raises(ValueError, match="trunk: a level whose procedures observe different entries"):
    PHPLevel(2, 5, (4,), hidden=(8,), observes=((0,), None), trunk=4, rngs=nnx.Rngs(0))
  with pytest.raises(ValueError, match="trunk"):
    PHPLevel(2, 5, (4,), hidden=(8,), trunk=0, rngs=nnx.Rngs(0))


def test_a_hierarchy_with_trunks_saves_loads_and_acts_the_same(tmp_path):
  from php_jax.training import checkpoint
  task = tasks.get("addition")
  hierarchy = PHPHierarchy(task.spec, hidden=(8,), trunk=5, rngs=nnx.Rngs(2))
  checkpoint.save_hierarchy(str(tmp_path), "addition", hierarchy, (8,), [4, 4, 4])
  assert checkpoint.trunk_width(hierarchy) == 5
  _, loaded = checkpoint.load_policy(str(tmp_path))
  assert checkpoint.trunk_width(loaded) == 5
  obs = jax.random.normal(jax.random.key(0), (task.spec.obs_dim,))
  for level in range(task.spec.num_levels):
    for proc in range(task.spec.num_procs(level)):
      args = (level, proc, 1, obs, jax.random.key(0))
      np.testing.assert_array_equal(hierarchy.operation(*args), loaded.operation(*args))
      assert bool(hierarchy.terminates(*args)) == bool(loaded.terminates(*args))


def test_networks_read_narrow_observations_as_their_float32_values():
  """A file's observations may be held as uint8 (`demos.compact_dtype`): every network, and the E-step over a
  whole hierarchy, give the same numbers as on the float32 values, and compute in float32."""
  from php_jax.demos import Demonstration, UNKNOWN
  from php_jax.flat import FlatPolicy
  from php_jax.training import objective
  rng = np.random.default_rng(0)
  narrow = rng.integers(0, 256, (6, 5)).astype(np.uint8)
  wide = narrow.astype(np.float32)
  for level in (PHPLevel(2, 5, (3,), hidden=(8,), rngs=nnx.Rngs(0)),
                PHPLevel(2, 5, (3,), hidden=(8,), trunk=4, rngs=nnx.Rngs(0))):
    assert level.encode(narrow).dtype == jnp.float32
    np.testing.assert_array_equal(level.encode(narrow), level.encode(wide))
  for root in (RootMLP(5, 3, (8,), rngs=nnx.Rngs(0)), RootLSTM(5, 3, 8, rngs=nnx.Rngs(0))):
    np.testing.assert_array_equal(root(narrow), root(wide))
  flat = FlatPolicy(5, (3,), 8, rngs=nnx.Rngs(0))
  actions, length = jnp.array([[0], [2], [1], [1], [0]]), jnp.int32(4)
  np.testing.assert_array_equal(flat.log_likelihood(narrow, actions, length), flat.log_likelihood(wide, actions, length))
  task = tasks.get("addition")
  hierarchy = PHPHierarchy(task.spec, hidden=(8,), rngs=nnx.Rngs(1))
  obs = rng.integers(0, 2, (2, 4, task.spec.obs_dim)).astype(np.uint8)
  unknown = np.full((2, 3, task.spec.num_levels), UNKNOWN, np.int32)
  demos = Demonstration(obs, rng.integers(0, 2, (2, 3, len(task.spec.action_sizes))).astype(np.int32), unknown,
                        unknown, np.array([3, 2], np.int32), np.zeros(2, bool))
  capacity = (4,) * task.spec.num_levels
  np.testing.assert_array_equal(
      objective.stack_log_likelihoods(hierarchy, demos, capacity),
      objective.stack_log_likelihoods(hierarchy, demos._replace(observations=obs.astype(np.float32)), capacity))
