"""The levels' action heads (`--action_head`): a head on each level's shared encoding that predicts every step's
elementary action. They leave the hierarchy's likelihood and its acting alone, add their own loss to training's
(joint and level-wise), are saved and loaded with the model, and are refused where there is no encoding for them to train."""
from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax.data import views
from php_jax.demos import Demonstration, UNKNOWN
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, RootMLP
from php_jax.training import checkpoint, objective
from php_jax.training.config import ConfigError, TrainConfig, check_levels

SPEC = HierarchySpec("heads", (("root",), ("a", "b"), ("c", "d")), (2, 3), 4)
CAPACITY = (3, 3, 2)


def _demos(seed: int, num: int = 3, steps: int = 5) -> Demonstration:
  rng = np.random.default_rng(seed)
  actions = np.stack([rng.integers(n, size=(num, steps)) for n in SPEC.action_sizes], -1).astype(np.int32)
  unknown = np.full((num, steps, SPEC.num_levels), UNKNOWN, np.int32)
  return Demonstration(rng.normal(size=(num, steps + 1, SPEC.obs_dim)).astype(np.float32), actions, unknown,
                       unknown, np.array([steps, steps - 2, steps - 1], np.int32)[:num], np.zeros(num, bool))


def _heads_loss_by_hand(hierarchy: PHPHierarchy, demos: Demonstration) -> float:
  """−Σ log p(a_t) of every level's head over each demonstration's real steps, averaged over demonstrations."""
  total = 0.0
  for b, length in enumerate(demos.length):
    for php in hierarchy.levels:
      features = np.asarray(php.features(jnp.asarray(demos.observations[b]), jnp.asarray(demos.actions[b])))
      logits = features @ np.asarray(php.action_head.kernel[...]) + np.asarray(php.action_head.bias[...])
      for t in range(length):
        start = 0
        for f, size in enumerate(SPEC.action_sizes):
          part = logits[t, start:start + size]
          total -= part[demos.actions[b, t, f]] - np.log(np.sum(np.exp(part)))
          start += size
  return total / len(demos.length)


@pytest.mark.parametrize("memory", [None, 6])
def test_the_heads_add_their_own_loss_and_leave_the_likelihood_alone(memory):
  hierarchy = PHPHierarchy(SPEC, hidden=(8,), trunk=5, memory=memory, action_head=True, rngs=nnx.Rngs(0))
  demos = _demos(1)
  buckets = views.demonstration_buckets(demos, 1)
  plain = float(objective.stack_loss(hierarchy, buckets, CAPACITY, 1.0))
  with_heads = float(objective.stack_loss(hierarchy, buckets, CAPACITY, 1.0, action_head=0.5))
  np.testing.assert_allclose(with_heads - plain, 0.5 * _heads_loss_by_hand(hierarchy, demos), rtol=1e-4)
  likelihoods = objective.stack_log_likelihoods(hierarchy, demos, CAPACITY)
  for php in hierarchy.levels:  # the heads are no part of the hierarchy's likelihood
    php.action_head.kernel[...] = php.action_head.kernel[...] + 1.0
  np.testing.assert_array_equal(objective.stack_log_likelihoods(hierarchy, demos, CAPACITY), likelihoods)


def test_the_heads_are_saved_and_loaded_with_the_model(tmp_path):
  hierarchy = PHPHierarchy(SPEC, hidden=(8,), trunk=5, action_head=True, rngs=nnx.Rngs(2))
  checkpoint.save_hierarchy(str(tmp_path), "heads", hierarchy, (8,), list(CAPACITY))
  assert json.loads((tmp_path / checkpoint.ARCHITECTURE_FILE).read_text())["action_head"] is True
  _, loaded = checkpoint.load_policy(str(tmp_path))
  assert loaded.action_head
  for ours, theirs in zip(hierarchy.levels, loaded.levels):
    np.testing.assert_array_equal(ours.action_head.kernel[...], theirs.action_head.kernel[...])
  obs = jax.random.normal(jax.random.key(0), (SPEC.obs_dim,))
  for level in range(SPEC.num_levels):  # the heads take no part in acting
    args = (level, 0, 1, obs, jax.random.key(0))
    np.testing.assert_array_equal(hierarchy.operation(*args), loaded.operation(*args))
  plain = PHPHierarchy(SPEC, hidden=(8,), trunk=5, rngs=nnx.Rngs(2))
  checkpoint.save_hierarchy(str(tmp_path / "plain"), "heads", plain, (8,))
  assert "action_head" not in json.loads((tmp_path / "plain" / checkpoint.ARCHITECTURE_FILE).read_text())


def test_heads_are_refused_without_an_encoding_to_train():
  with pytest.raises(ConfigError, match="^action_head: needs a shared encoding"):
    check_levels(SPEC, TrainConfig(action_head=1.0))
  check_levels(SPEC, TrainConfig(action_head=1.0, trunk=8))
  with pytest.raises(ConfigError, match="^action_head: must be a finite number ≥ 0"):
    TrainConfig(action_head=-1.0)


def test_level_wise_a_level_s_head_predicts_the_elementary_action_where_each_of_its_operations_starts():
  hierarchy = PHPHierarchy(SPEC, hidden=(8,), trunk=5, action_head=True, rngs=nnx.Rngs(1))
  demos = _demos(2)
  lowest = views.lowest_view(demos, SPEC.num_levels)
  np.testing.assert_array_equal(lowest.elementary, lowest.actions)
  procedures = np.zeros_like(lowest.procedures)
  counters = np.tile(np.array([0, 1, 0, 0, 1], np.int32), (3, 1))  # the level-2 calls start at steps 0, 2, 3
  above = views.view_above(demos, lowest, 2, procedures, counters)
  for b, length in enumerate(above.length):
    np.testing.assert_array_equal(above.elementary[b, :length], demos.actions[b, above.times[b, :length]])
  model = objective.LevelModel(hierarchy.levels[1], RootMLP(SPEC.obs_dim, 2, (8,), rngs=nnx.Rngs(0)))
  [bucket] = [views.device_view(b) for b in views.length_buckets(above, 1)]
  plain = float(objective.level_loss(model, [bucket], 4, 1.0))
  with_head = float(objective.level_loss(model, [bucket], 4, 1.0, action_head=2.0))
  php, by_hand = hierarchy.levels[1], 0.0
  for b, length in enumerate(above.length):
    features = np.asarray(php.encode(jnp.asarray(above.observations[b, :length])))
    logits = features @ np.asarray(php.action_head.kernel[...]) + np.asarray(php.action_head.bias[...])
    for t in range(length):
      for part, action in zip(np.split(logits[t], [2]), above.elementary[b, t]):
        by_hand -= part[action] - np.log(np.sum(np.exp(part)))
  np.testing.assert_allclose(with_head - plain, 2.0 * by_hand / len(above.length), rtol=1e-4)
