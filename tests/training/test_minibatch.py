"""Minibatch Expectation–Gradient (`--batch_size`): what each update draws, that a minibatch's loss estimates the
full loss, and that a fit on minibatches trains, resumes to the same result, and is a full-batch fit where the
batch holds every demonstration."""
import dataclasses
import itertools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax import fitting, sharding
from php_jax.data import views
from php_jax.envs import datasets, tasks
from php_jax.training import checkpoint, joint, levelwise, networks, objective
from php_jax.training import config as config_module
from php_jax.training.config import ConfigError, TrainConfig

NANOCRAFT = tasks.get("nanocraft")


def _drawn(batch_size, sizes, iteration, seed=0):
  """The rows (values of an `id` leaf) minibatched's loss receives from buckets of the given sizes."""
  buckets = [{"id": jnp.arange(size) + 100 * b} for b, size in enumerate(sizes)]
  seen = []

  def loss(model, buckets):
    seen.append([np.asarray(bucket["id"]).tolist() for bucket in buckets])
    return 0.0
  fitting.minibatched(loss, batch_size, seed).fn(None, jnp.int32(iteration), buckets)
  return seen[0]


def test_each_update_draws_distinct_rows_of_every_bucket_in_proportion_the_same_for_the_same_update():
  drawn = _drawn(6, [10, 20, 2], iteration=3)
  assert [len(rows) for rows in drawn] == [2, 4, 1]  # 6 · 10/32, 6 · 20/32, at least 1
  assert all(len(set(rows)) == len(rows) for rows in drawn)
  assert all(100 * b <= r < 100 * b + n for b, (rows, n) in enumerate(zip(drawn, [10, 20, 2])) for r in rows)
  assert _drawn(6, [10, 20, 2], iteration=3) == drawn
  others = [_drawn(6, [10, 20, 2], iteration=i) for i in range(4, 12)] + [_drawn(6, [10, 20, 2], 3, seed=1)]
  assert any(o != drawn for o in others)
  assert [sorted(rows) for rows in _drawn(100, [3, 4], iteration=0)] == [[0, 1, 2], [100, 101, 102, 103]]


def test_minibatches_drawn_on_the_host_are_the_rows_the_compiled_update_would_draw():
  sizes = [10, 20, 2]
  draw = fitting.host_minibatches([{"id": np.arange(size) + 100 * b} for b, size in enumerate(sizes)], 6, seed=4)
  for iteration in (0, 1, 7):
    assert [bucket["id"].tolist() for bucket in draw(iteration)] == _drawn(6, sizes, iteration, seed=4)


def test_without_a_mesh_the_update_is_compiled_once_for_the_minibatch_and_never_sees_the_whole_set():
  """fit draws on the host: the compiled update's data are the minibatch's rows alone, traced once over every
  update; its result is that of drawing inside the update."""
  data = [(np.linspace(-1, 1, 40, dtype=np.float32).reshape(20, 2), np.arange(20, dtype=np.float32))]
  traced = []

  def loss(model, buckets):
    [(x, y)] = buckets
    traced.append(x.shape)
    return jnp.mean((model(x)[:, 0] - y) ** 2)
  schedule = fitting.Schedule(12, 1e-2, 4, batch_size=5, batch_seed=3)
  host = nnx.Linear(2, 1, rngs=nnx.Rngs(0))
  fitting.fit(host, loss, schedule, fitting.Hooks(log=lambda row: None), args=(data,))
  assert traced == [(5, 2)]
  mesh = jax.sharding.Mesh(np.asarray(jax.devices()[:1]), (sharding.AXIS,))
  inside = nnx.Linear(2, 1, rngs=nnx.Rngs(0))
  fitting.fit(inside, loss, schedule, fitting.Hooks(log=lambda row: None), args=(sharding.put(data, mesh),),
              mesh=mesh)
  for a, b in zip(jax.tree.leaves(nnx.state(host)), jax.tree.leaves(nnx.state(inside))):
    np.testing.assert_allclose(a, b, rtol=1e-6)


def test_joint_training_on_minibatches_keeps_its_demonstrations_off_the_device():
  demos = jax.tree.map(np.asarray, datasets.training_demos(NANOCRAFT, 2, 8, 8))  # as read from a file
  whole = views.length_buckets(demos, 1)[0].observations.shape
  before = {id(a) for a in jax.live_arrays()}  # the environments' own arrays (the data set they gave)
  seen = []

  def validate(hierarchy):
    seen.append(any(a.shape == whole and id(a) not in before for a in jax.live_arrays()))
    return 0.0
  config = TrainConfig(iterations=4, learning_rate=1e-2, hidden=(8,), eval_every=2, training="joint", seed=2,
                       length_buckets=1)
  joint.train_joint(NANOCRAFT.spec, demos, dataclasses.replace(config, batch_size=3), validate, lambda row: None)
  assert seen == [False, False]
  joint.train_joint(NANOCRAFT.spec, demos, config, validate, lambda row: None)  # the full batch: all of it
  assert seen[2:] == [True, True]


def test_a_minibatch_loss_averaged_over_every_minibatch_is_the_full_loss():
  """With every demonstration weighted alike, the mean over all equally likely minibatches of a bucket of the
  per-demonstration loss is the full batch's (the gradient's too, being linear)."""
  demos = datasets.training_demos(NANOCRAFT, 1, 5, 0)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, TrainConfig(hidden=(8,), seed=1))
  capacity = (6, 8, 8)
  bucket = views.device_demonstrations(demos)

  def loss(h, rows):
    picked = jax.tree.map(lambda x: x[np.asarray(rows)], bucket)
    return objective.stack_loss(h, [picked], capacity, strong_weight=1.0)
  full = float(loss(hierarchy, range(5)))
  means = [float(loss(hierarchy, rows)) for rows in itertools.combinations(range(5), 2)]
  np.testing.assert_allclose(np.mean(means), full, rtol=1e-5)
  assert np.std(means) > 0  # the minibatches do differ


def test_a_batch_holding_every_demonstration_is_the_full_batch_fit():
  demos = datasets.training_demos(NANOCRAFT, 2, 6, 2)
  config = TrainConfig(iterations=6, learning_rate=1e-2, hidden=(8,), eval_every=3, training="joint", seed=2,
                       length_buckets=2)
  full, _ = joint.train_joint(NANOCRAFT.spec, demos, dataclasses.replace(config, batch_size=0),
                              log=lambda row: None)
  for batch_size in (6, None):  # every one of them; unset, on so few
    batched, _ = joint.train_joint(NANOCRAFT.spec, demos, dataclasses.replace(config, batch_size=batch_size),
                                   log=lambda row: None)
    for a, b in zip(jax.tree.leaves(nnx.state(full, nnx.Param)), jax.tree.leaves(nnx.state(batched, nnx.Param))):
      np.testing.assert_array_equal(a, b)


def test_an_unset_batch_size_is_every_demonstration_up_to_the_limit_and_the_default_minibatch_above():
  assert config_module.batch_size_for(TrainConfig(), config_module.FULL_BATCH_MAX) == 0
  assert config_module.batch_size_for(TrainConfig(), config_module.FULL_BATCH_MAX + 1) == \
      config_module.DEFAULT_BATCH_SIZE
  assert config_module.batch_size_for(TrainConfig(batch_size=0), 10**5) == 0
  assert config_module.batch_size_for(TrainConfig(batch_size=5), 3) == 5


def test_minibatch_training_learns_and_an_interrupted_fit_resumes_to_the_same_result(tmp_path):
  demos = datasets.training_demos(NANOCRAFT, 2, 8, 8)
  config = TrainConfig(iterations=30, learning_rate=1e-2, hidden=(16,), eval_every=10, training="joint", seed=2,
                       batch_size=3, length_buckets=2)
  rows = []
  reference, report = joint.train_joint(NANOCRAFT.spec, demos, config, log=rows.append)
  losses = [r["loss"] for r in rows if "loss" in r]
  assert losses[-1] < losses[0]

  def stop_at_20(row):
    if row.get("iteration") == 20:
      raise KeyboardInterrupt
  path = str(tmp_path / checkpoint.TRAINING_DIR)
  with pytest.raises(KeyboardInterrupt):
    joint.train_joint(NANOCRAFT.spec, demos, config, log=stop_at_20, checkpoint_path=path)
  resumed, _ = joint.train_joint(NANOCRAFT.spec, demos, config, log=lambda row: None, checkpoint_path=path)
  for a, b in zip(jax.tree.leaves(nnx.state(reference, nnx.Param)), jax.tree.leaves(nnx.state(resumed, nnx.Param))):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)


def test_level_wise_training_on_minibatches_alone_and_as_seeds_draws_each_seeds_own():
  """Level-wise, a seed trained alone and the same seed trained beside another draw their own minibatches: at
  the lowest level, where both seeds' views are all real (no padding), the same losses."""
  demos = [datasets.training_demos(NANOCRAFT, s, 6, 6) for s in (3, 4)]
  configs = [TrainConfig(iterations=4, eval_every=2, hidden=(8,), root="mlp", root_hidden=8, learning_rate=1e-2,
                         length_buckets=1, batch_size=2, seed=s) for s in (3, 4)]
  rows = {0: [], 1: []}
  levelwise.train_seeds(NANOCRAFT.spec, demos, configs, [lambda h: 0.0] * 2, log=lambda s, row: rows[s].append(row))
  for s in (0, 1):
    alone = []
    levelwise.train_hierarchy(NANOCRAFT.spec, demos[s], configs[s], lambda h: 0.0, log=alone.append)
    lowest = [r["loss"] for r in alone if r.get("level") == 2 and "loss" in r]
    np.testing.assert_allclose([r["loss"] for r in rows[s] if r.get("level") == 2 and "loss" in r], lowest,
                               rtol=1e-4)


def test_a_negative_batch_size_is_refused():
  with pytest.raises(ConfigError, match="batch_size: must be a non-negative integer"):
    TrainConfig(batch_size=-1)
