"""Data parallelism (php_jax.sharding): demonstrations split over 4 CPU devices, in one process or in two
(jax.distributed), give the one-device losses, gradients and training. XLA_FLAGS must be set before JAX
starts, so the 4-device side runs in a subprocess."""
from __future__ import annotations

import json
import os
import pathlib
import socket
import subprocess
import sys

import numpy as np
import pytest

from php_jax import sharding
from php_jax.data import views
from php_jax.envs import datasets, tasks
from php_jax.training import joint

ROOT = pathlib.Path(__file__).resolve().parents[2]
FOUR_DEVICES = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4"}
# For the losses, gradients and fits compared one device against four: both compiled without LLVM's
# optimizations, which take most of their compile time and are no part of what is compared.
FOUR_DEVICES_UNOPTIMIZED = {**FOUR_DEVICES,
                            "XLA_FLAGS": FOUR_DEVICES["XLA_FLAGS"] + " --xla_backend_optimization_level=0"}
NANOCRAFT = tasks.get("nanocraft")

# In a 4-device process: the level loss (lowest level) and the joint loss with their gradients, one device
# against the 4-device mesh, on 7 demonstrations in one length bucket (padded to 8); then 10 Adam iterations
# of the level loss each way. Prints one JSON line. (One bucket: each compiles in half the time of two.)
CHECK = r"""
import json
import jax
import numpy as np
from flax import nnx
from php_jax import fitting, sharding
from php_jax.data import views
from php_jax.envs import datasets, tasks
from php_jax.training import joint, levelwise, networks, objective
from php_jax.training.config import TrainConfig

task = tasks.get("nanocraft")
demos = datasets.training_demos(task, seed=3, num_demos=7, num_strong=3)
config = TrainConfig(hidden=(8,), root="mlp", root_hidden=8, seed=2, strong_weight=2.0)
mesh = sharding.data_mesh()
out = {"devices": len(jax.devices())}

def compare(value_and_grad, params, one, many):
  (loss_1, grads_1), (loss_4, grads_4) = value_and_grad(params, one), value_and_grad(params, many)
  leaves_1, leaves_4 = jax.tree.leaves(grads_1), jax.tree.leaves(grads_4)
  scale = max(float(np.max(np.abs(g))) for g in leaves_1)
  return {"loss": [float(loss_1), float(loss_4)], "grad_scale": scale,
          "grad_diff": max(float(np.max(np.abs(a - b))) for a, b in zip(leaves_1, leaves_4)),
          "finite": all(bool(np.all(np.isfinite(g))) for g in leaves_4)}

def shards(buckets):  # per bucket, per array: the leading size each device holds, and on how many devices
  return [[[int(s.data.shape[0]) for s in x.addressable_shards] + [len({s.device for s in x.addressable_shards})]
           for x in jax.tree.leaves(b)] for b in buckets]

level = task.spec.num_levels - 1
view = views.lowest_view(demos, task.spec.num_levels)
capacity = levelwise.level_capacity(view, level, config)
def level_model():
  return objective.LevelModel(networks.make_hierarchy(task.spec, config).levels[level],
                              networks.make_root(task.spec, level, config))
graphdef, params, rest = nnx.split(level_model(), nnx.Param, ...)
level_grad = jax.jit(jax.value_and_grad(
    lambda p, b: objective.level_loss(nnx.merge(graphdef, p, rest), b, capacity, config.strong_weight)))
parts = views.length_buckets(view, 1)
one = [views.device_view(b) for b in parts]
many = [views.device_view(b, mesh) for b in parts]
out["level"] = compare(level_grad, params, one, many)
out["level_sizes"] = [len(b.length) for b in parts]
out["level_shards"] = shards(many)
out["level_real"] = [np.asarray(b.real).tolist() for b in many]

def fit(buckets, mesh):
  model = level_model()
  progress = fitting.fit(model, lambda m, b: objective.level_loss(m, b, capacity, config.strong_weight),
                         fitting.Schedule(10, 1e-2, 5), fitting.Hooks(log=lambda row: None), args=(buckets,),
                         mesh=mesh)
  return progress.losses, jax.tree.leaves(nnx.state(model, nnx.Param))
(losses_1, params_1), (losses_4, params_4) = fit(one, None), fit(many, mesh)
out["fit_losses"] = [losses_1, losses_4]
out["fit_param_diff"] = max(float(np.max(np.abs(a - b))) for a, b in zip(params_1, params_4))
out["fit_params_on_default"] = all(p.devices() == {jax.devices()[0]} for p in params_4)

two = [demos, datasets.training_demos(task, seed=4, num_demos=6, num_strong=2)]  # seeds as one program
two_views = [views.lowest_view(d, task.spec.num_levels) for d in two]
two_capacity = max(levelwise.level_capacity(v, level, config) for v in two_views)
def fit_seeds(mesh):
  buckets = views.stack_seeds([views.length_buckets(v, 1) for v in two_views], mesh)
  progress = fitting.fit_seeds([level_model(), level_model()],
                               lambda m, b: objective.level_loss(m, b, two_capacity, config.strong_weight),
                               fitting.Schedule(10, 1e-2, 5), fitting.Hooks(log=lambda s, row: None),
                               args=(buckets,), mesh=mesh)
  return [p.losses for p in progress], buckets
(out["seeds_losses_1"], _), (out["seeds_losses_4"], buckets) = fit_seeds(None), fit_seeds(mesh)
out["seeds_shards"] = [[int(s.data.shape[1]) for s in x.addressable_shards] for x in jax.tree.leaves(buckets[0])]

hierarchy = networks.make_hierarchy(task.spec, config)
graphdef, params, rest = nnx.split(hierarchy, nnx.Param, ...)
capacities = joint.joint_capacity(demos, task.spec, config)
joint_grad = jax.jit(jax.value_and_grad(
    lambda p, b: objective.stack_loss(nnx.merge(graphdef, p, rest), b, capacities, config.strong_weight)))
one, many = views.demonstration_buckets(demos, 1), views.demonstration_buckets(demos, 1, mesh)
out["joint"] = compare(joint_grad, params, one, many)
out["joint_shards"] = shards(many)
print(json.dumps(out))
"""


def test_one_device_batches_are_unpadded_and_unsplit():
  demos = datasets.training_demos(NANOCRAFT, seed=3, num_demos=7, num_strong=3)
  view = views.lowest_view(demos, NANOCRAFT.spec.num_levels)
  assert sharding.data_mesh() is None  # this process has one CPU device
  batch = views.device_view(view)
  assert batch.observations.shape == view.observations.shape and np.all(batch.real)
  np.testing.assert_array_equal(batch.actions, view.actions)
  for bucket, real in views.demonstration_buckets(demos, 2):
    assert len(bucket.length) in (3, 4) and np.all(real)


def test_sharded_losses_gradients_and_fit_equal_one_device():
  proc = subprocess.run([sys.executable, "-c", CHECK], capture_output=True, text=True, timeout=300, cwd=ROOT,
                        env=FOUR_DEVICES_UNOPTIMIZED)
  assert proc.returncode == 0, proc.stderr[-3000:]
  out = json.loads(proc.stdout.splitlines()[-1])
  assert out["devices"] == 4
  for name in ("level", "joint"):
    result = out[name]
    np.testing.assert_allclose(result["loss"][1], result["loss"][0], rtol=1e-5)
    assert result["finite"] and result["grad_diff"] <= 1e-5 * max(1.0, result["grad_scale"]), result
  # 7 views padded with one copy (real False); every array split 2 + 2 + 2 + 2 over the 4 devices.
  assert out["level_sizes"] == [7]
  assert out["level_real"] == [[True] * 7 + [False]]
  for shards in (out["level_shards"], out["joint_shards"]):
    assert len(shards) == 1 and all(sizes == [2, 2, 2, 2, 4] for sizes in shards[0])
  losses_1, losses_4 = out["fit_losses"]
  assert [i for i, _ in losses_1] == [i for i, _ in losses_4] == [5, 10]
  np.testing.assert_allclose([l for _, l in losses_4], [l for _, l in losses_1], rtol=1e-4)
  assert out["fit_param_diff"] < 1e-4
  assert out["fit_params_on_default"]  # the model gets its parameters back on the default device
  # Two seeds (7 and 6 views, both padded to 8): each seed's losses as on one device, B split 2 + 2 + 2 + 2.
  for seed_1, seed_4 in zip(out["seeds_losses_1"], out["seeds_losses_4"]):
    np.testing.assert_allclose([l for _, l in seed_4], [l for _, l in seed_1], rtol=1e-4)
  assert all(sizes == [2, 2, 2, 2] for sizes in out["seeds_shards"])


def _free_port() -> int:
  with socket.socket() as s:
    s.bind(("localhost", 0))
    return s.getsockname()[1]


@pytest.mark.slow
def test_training_on_four_devices_or_two_processes_gives_the_one_device_results(tmp_path):
  command = [sys.executable, "-m", "experiments.train", "--task=nanocraft", "--num_demos=7", "--num_strong=3",
             "--training=levelwise", "--iterations=20", "--eval_every=10", "--hidden=16", "--root=mlp", "--num_test=50"]
  two_processes = {**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=2",
                   "JAX_COORDINATOR_ADDRESS": f"localhost:{_free_port()}", "JAX_NUM_PROCESSES": "2"}
  runs = {"one": (os.environ, []), "four": (FOUR_DEVICES, []),
          **{f"process{i}": ({**two_processes, "JAX_PROCESS_ID": str(i)}, ["--distributed"]) for i in (0, 1)}}
  procs = {name: subprocess.Popen(command + [f"--workdir={tmp_path / name.rstrip('01')}", *flags], cwd=ROOT,
                                  env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
           for name, (env, flags) in runs.items()}
  for name, proc in procs.items():
    output = proc.communicate(timeout=1200)[0]
    assert proc.returncode == 0, (name, output[-3000:])
  results = {name: json.loads((tmp_path / name / "results.json").read_text()) for name in ("one", "four", "process")}
  assert [(r["versions"]["devices"], r["versions"]["processes"]) for r in results.values()] == [(1, 1), (4, 1), (4, 2)]
  one = results["one"]
  for name in ("four", "process"):
    assert results[name]["test"] == one["test"]
    for level, entry in one["levels"].items():
      other = results[name]["levels"][level]
      np.testing.assert_allclose(other["final_loss"], entry["final_loss"], rtol=1e-5)
      assert (other.get("decoding_agreement"), other["best_iteration"]) == (entry.get("decoding_agreement"),
                                                                            entry["best_iteration"])
  # The two processes wrote one run: every metrics row once.
  assert len((tmp_path / "process" / "metrics.jsonl").read_text().splitlines()) == len(
      (tmp_path / "one" / "metrics.jsonl").read_text().splitlines())


LOADED = """
import sys
import jax.numpy as jnp
import numpy as np
from flax import nnx
from php_jax import fitting, sharding
if sys.argv[1] == "async":  # what the loop did before it waited for each program on CPU devices
  sharding.one_program_at_a_time = lambda mesh: False
mesh = sharding.data_mesh()
data = sharding.put(np.ones((64, 256, 64), np.float32), mesh)
model = nnx.Linear(64, 64, rngs=nnx.Rngs(0))
fitting.fit(model, lambda m, x: jnp.sum(jnp.tanh(m(x)) ** 2), fitting.Schedule(3000, 1e-6, 1000),
            fitting.Hooks(log=lambda row: None), args=(data,), mesh=mesh)
print("done")
"""


def loaded_fit(mode: str) -> subprocess.CompletedProcess:
  """A 3000-step data-parallel fit over 4 CPU devices while 4 busy processes load the machine."""
  busy = [subprocess.Popen([sys.executable, "-c", "while True: pass"]) for _ in range(4)]
  try:
    return subprocess.run([sys.executable, "-c", LOADED, mode], env=FOUR_DEVICES, capture_output=True, text=True,
                          timeout=900, cwd=ROOT)
  finally:
    for proc in busy:
      proc.kill()


@pytest.mark.slow
def test_a_data_parallel_fit_on_cpu_devices_completes_on_a_loaded_machine():
  """XLA's in-process all-reduce aborts the process when one device falls 40 s behind, which several
  programs in flight on a loaded machine bring about; the loop waits for each program on CPU devices."""
  proc = loaded_fit("wait")
  assert proc.returncode == 0 and "done" in proc.stdout, proc.stderr[-2000:]
