"""Seeds trained as one program (php_jax.training.levelwise.train_seeds) give each seed's separate run, and resume."""
import dataclasses
import json
import os
import subprocess
import sys

import jax
import numpy as np
import pytest
from flax import nnx

from php_jax import fitting
from php_jax.data import views
from php_jax.envs import datasets, evaluation, nanocraft, nanocraft_task, tasks
from php_jax.training import checkpoint, levelwise, networks, objective
from tests import processes
from php_jax.training.config import TrainConfig, prepare

NANOCRAFT = tasks.get("nanocraft")
CONFIG = TrainConfig(iterations=20, eval_every=10, hidden=(8,), root="mlp", root_hidden=8,
                           learning_rate=1e-2, decode="sample", length_buckets=1)
SEEDS = (3, 4)
ROOT = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
NUM_DEMOS = {3: 6, 4: 5}  # seeds with different numbers of demonstrations: their batches are padded alike


class _Interrupt(Exception):
  pass


def _demos(seed):
  problems = nanocraft_task.random_problems(seed, NUM_DEMOS[seed])
  return datasets.oracle_demonstrations(NANOCRAFT, nanocraft_task.make_states(problems), 2,
                                        nanocraft.ORACLE_STEP_BUDGET)


def _validator(seed):
  problems = nanocraft_task.random_problems(seed + 100, 3)
  return lambda h: float(np.mean([o["correct"] for o in evaluation.solve(NANOCRAFT, h, problems)]))


def _params(hierarchy):
  return jax.tree.leaves(nnx.state(hierarchy, nnx.Param))


def test_each_seeds_loss_and_fit_inside_the_stacked_program_are_its_own():
  """Two seeds' views (6 and 5 demonstrations, all annotated, so every level's view is the supervisor's) padded
  into one stack, each seed's capacity masked inside the larger: the vmapped losses and a few Adam steps equal
  each seed's own (level 1, where the two seeds' capacities differ)."""
  level = 1
  demos = [_demos(s)._replace(strong=np.ones(NUM_DEMOS[s], bool)) for s in SEEDS]
  configs = [prepare(NANOCRAFT.spec, d, dataclasses.replace(CONFIG, seed=s)) for d, s in zip(demos, SEEDS)]
  level_views = [views.annotated_views(d, NANOCRAFT.spec.num_levels)[level] for d in demos]
  capacities = [levelwise.level_capacity(v, level, c) for v, c in zip(level_views, configs)]
  assert capacities[0] != capacities[1]

  def models():
    return [levelwise.level_model(NANOCRAFT.spec, networks.make_hierarchy(NANOCRAFT.spec, c), level, c) for c in configs]

  alone = []
  for model, view, capacity, config in zip(models(), level_views, capacities, configs):
    buckets = [views.device_view(view)]
    progress = fitting.fit(model, lambda m, b: objective.level_loss(m, b, capacity, config.strong_weight),
                           fitting.Schedule(3, 1e-2, 1), fitting.Hooks(log=lambda row: None), args=(buckets,))
    alone.append((progress.losses, model))
  stacked = views.stack_seeds([[v] for v in level_views])
  together_models = models()
  progress = fitting.fit_seeds(
      together_models, lambda m, b, w, used: objective.level_loss(m, b, max(capacities), w, used),
      fitting.Schedule(3, 1e-2, 1), fitting.Hooks(log=lambda s, row: None),
      args=(stacked, np.asarray([c.strong_weight for c in configs], np.float32), np.asarray(capacities, np.int32)))
  for (losses, model), p, together in zip(alone, progress, together_models):
    np.testing.assert_allclose([l for _, l in p.losses], [l for _, l in losses], rtol=1e-5)
    for a, b in zip(_params(model), _params(together)):
      np.testing.assert_allclose(a, b, rtol=1e-4, atol=1e-6)


@pytest.mark.slow
def test_seeds_trained_together_match_their_separate_runs():
  demos = [_demos(s) for s in SEEDS]
  configs = [dataclasses.replace(CONFIG, seed=s) for s in SEEDS]
  rows = {s: [] for s in range(len(SEEDS))}
  together = levelwise.train_seeds(NANOCRAFT.spec, demos, configs, [_validator(s) for s in SEEDS],
                               log=lambda s, row: rows[s].append(row))
  capacities = [[report[level]["capacity"] for level in range(3)] for _, report in together]
  assert capacities[0] != capacities[1]  # each seed's own capacity, inside the padded one
  for s, (seed, (hierarchy, report)) in enumerate(zip(SEEDS, together)):
    separate_rows = []
    alone, alone_report = levelwise.train_hierarchy(NANOCRAFT.spec, demos[s], configs[s], _validator(seed),
                                                log=separate_rows.append)
    for a, b in zip(_params(alone), _params(hierarchy)):
      np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)
    for level in range(3):
      np.testing.assert_allclose(np.asarray(report[level]["losses"]), np.asarray(alone_report[level]["losses"]),
                                 rtol=1e-4)
      for key in ("capacity", "best_iteration", "validation", "decoding_agreement"):
        assert report[level].get(key) == alone_report[level].get(key), (seed, level, key)
    assert [sorted(r) for r in rows[s]] == [sorted(r) for r in separate_rows]
    for ours, theirs in zip(rows[s], separate_rows):
      assert {k: v for k, v in ours.items() if k != "loss"} == {k: v for k, v in theirs.items() if k != "loss"}
      assert ours.get("loss", 0.0) == pytest.approx(theirs.get("loss", 0.0), rel=1e-4)


@pytest.mark.slow
def test_interrupted_seeds_resume_to_the_same_result(tmp_path):
  demos = [_demos(s) for s in SEEDS]
  configs = [dataclasses.replace(CONFIG, seed=s, strong_warmup=10) for s in SEEDS]
  validate = [_validator(s) for s in SEEDS]

  def run(path, stop_at=None):
    def log(s, row):
      if stop_at and s == 1 and (row.get("level"), row.get("iteration")) == stop_at:
        raise _Interrupt
    return levelwise.train_seeds(NANOCRAFT.spec, demos, configs, validate, log=log, checkpoint_path=path)

  reference = run(str(tmp_path / "uninterrupted"))
  path = str(tmp_path / "interrupted")
  for stop_at in [(2, 10), (1, 20), (0, 20)]:  # the warm-up's end, a level's last iteration, the root mid-way
    with pytest.raises(_Interrupt):
      run(path, stop_at)
  resumed = run(path)
  for (a, a_report), (b, b_report) in zip(reference, resumed):
    for x, y in zip(_params(a), _params(b)):
      np.testing.assert_array_equal(x, y)
    assert a_report[0]["losses"] == b_report[0]["losses"] and a_report[0]["best_iteration"] == b_report[0][
        "best_iteration"]
  with pytest.raises(checkpoint.CheckpointError, match="holds 2 seeds; this run has 1"):
    levelwise.train_seeds(NANOCRAFT.spec, demos[:1], configs[:1], validate[:1], checkpoint_path=path)
  with pytest.raises(checkpoint.CheckpointError, match="other settings.*iterations: 20 there, 40 here"):
    levelwise.train_seeds(NANOCRAFT.spec, demos, [dataclasses.replace(c, iterations=40) for c in configs], validate,
                      checkpoint_path=path)
  with pytest.raises(ValueError, match="same settings but for their seed"):
    levelwise.train_seeds(NANOCRAFT.spec, demos, [configs[0], dataclasses.replace(configs[1], hidden=(4,))])


BASE = [sys.executable, "-m", "experiments.train", "--task=tests.test_task_interface:COUNTDOWN", "--num_strong=2",
        "--root=mlp", "--iterations=20", "--eval_every=10"]


@pytest.mark.slow
def test_the_training_command_with_seeds_writes_each_seeds_separate_run(tmp_path):
  base = BASE
  together = subprocess.run(base + ["--seeds=0,1", f"--workdir={tmp_path / 'seeds'}"], capture_output=True,
                            text=True, timeout=600, cwd=ROOT)
  assert together.returncode == 0, together.stderr[-3000:]
  alone = subprocess.run(base + ["--seed=1", f"--workdir={tmp_path / 'alone'}"], capture_output=True, text=True,
                         timeout=600, cwd=ROOT)
  assert alone.returncode == 0, alone.stderr[-3000:]
  run = tmp_path / "seeds" / "seed=1"
  assert sorted(p.name for p in run.iterdir()) == sorted(p.name for p in (tmp_path / "alone").iterdir())
  ours, theirs = (json.loads((d / "results.json").read_text()) for d in (run, tmp_path / "alone"))
  assert ours["test"] == theirs["test"] and ours["config"] == theirs["config"] and ours["seed"] == 1
  assert ours["trained_with_seeds"] == [0, 1] and "trained_with_seeds" not in theirs
  for level in ("0", "1", "2"):
    for key in ("capacity", "best_iteration", "validation", "decoding_agreement"):
      assert ours["levels"][level].get(key) == theirs["levels"][level].get(key)
  _, ours_model = checkpoint.load_policy(str(run))
  _, theirs_model = checkpoint.load_policy(str(tmp_path / "alone"))
  for a, b in zip(_params(ours_model), _params(theirs_model)):
    np.testing.assert_allclose(a, b, rtol=1e-3, atol=1e-4)
  assert json.loads((tmp_path / "seeds" / "seed=0" / "results.json").read_text())["seed"] == 0


def test_the_training_command_refuses_seeds_with_flags_they_do_not_go_with(tmp_path):
  without_root = [a for a in BASE if a != "--root=mlp"]  # --root is level-wise training's
  nanocraft = [sys.executable, "-m", "experiments.nanocraft", "--num_demos=4"]
  joint_task = [a.replace("COUNTDOWN", "COUNTDOWN_JOINT") for a in without_root]  # joint by its defaults
  cases = [
      # Seed 0's annotated demonstration shows build_u placing a block, seed 1's does not. (First: it makes the
      # demonstrations, the longest of the runs.)
      (nanocraft + ["--call_graph=operations"], "--num_strong=1",
       "--seeds: the seeds' annotated demonstrations show different call graphs (operations)"),
      (BASE, "--seed=2", "--seeds and --seed: give one"), (BASE, "--seeds=1,1", "distinct"),
      (without_root, "--training=joint", "--seeds trains level-wise only; this run trains jointly (--training=joint)"),
      (joint_task, "--num_strong=1", "jointly (--training=joint, the task default): add --training=levelwise"),
      (joint_task, "--strong_warmup=10", "--strong_warmup: applies to level-wise training only")]
  # Run at the same time, each with its own workdir.
  procs = processes.run_all([command + ["--seeds=0,1", flag, f"--workdir={tmp_path / f'bad{i}'}"]
                             for i, (command, flag, _) in enumerate(cases)], capture_output=True, text=True,
                            timeout=600, cwd=ROOT)
  for i, ((_, _, message), bad) in enumerate(zip(cases, procs)):
    assert bad.returncode == 2 and message in bad.stderr and bad.stderr.count("\n") == 1, bad.stderr[-2000:]
    assert not (tmp_path / f"bad{i}").exists()
