"""A task defined here, outside the library, goes through every generic part: oracle demonstrations, training
one level, the training command, and evaluate (by its import path, tests.test_task_interface:COUNTDOWN)."""
import dataclasses
import json
import pathlib
import signal
import subprocess
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import struct

from php_jax import demos, fitting
from php_jax.data import views
from php_jax.envs import datasets, evaluation, tasks
from php_jax.envs.task import Task, TrainingDefaults
from php_jax.hierarchy import HierarchySpec
from php_jax.training import checkpoint, levelwise, networks, objective, resume, run
from php_jax.training import config as config_lib
from tests import processes
from tests.saved import file_bytes, leftovers, saved_model
from php_jax.training.config import TrainConfig

ROOT = pathlib.Path(__file__).resolve().parents[1]
DEC, REST = 0, 1  # elementary actions: decrement the counter, or do nothing


@struct.dataclass
class CounterState:
  count: jax.Array
  failed: jax.Array


class Counter:
  """A counter that must be brought to 0; decrementing 0 is invalid. Observation: (count = 0, count > 0)."""

  @staticmethod
  def observe(state):
    return jnp.stack([state.count == 0, state.count > 0]).astype(jnp.float32)

  @staticmethod
  def step(state, action):
    ok = (action[0] == REST) | ((action[0] == DEC) & (state.count > 0))
    return CounterState(jnp.where(ok & (action[0] == DEC), state.count - 1, state.count), state.failed | ~ok)


SPEC = HierarchySpec(name="countdown", levels=(("countdown",), ("tick",), ("dec", "rest")), action_sizes=(2,),
                     obs_dim=2)


@struct.dataclass
class CountdownOracle:
  """countdown calls tick until the count is 0; tick = dec then rest; dec = DEC; rest = REST."""

  def operation(self, level, proc, tau, obs, key):
    if level == 0:
      return jnp.zeros(1, jnp.int32)
    if level == 1:
      return jnp.clip(tau, 0, 1)[None].astype(jnp.int32)
    return jnp.where(proc == 0, DEC, REST)[None].astype(jnp.int32)

  def terminates(self, level, proc, tau, obs, key):
    if level == 0:
      return obs[0] > 0.5
    if level == 1:
      return tau >= 1
    return tau >= 0


def _problems(seed, num, length=None):
  rng = np.random.default_rng(seed)
  return [int(k) for k in (rng.integers(1, 6, num) if length is None else [length] * num)]


def _parse(obj):
  if not isinstance(obj.get("count"), int) or obj["count"] < 1:
    raise ValueError('needs a positive integer "count"')
  return obj["count"]


COUNTDOWN = Task(
    name="countdown", env=Counter, spec=SPEC, oracle=CountdownOracle(),
    training_problems=lambda seed, num: _problems(seed, num), validation_problems=_problems,
    test_problems=_problems, bucket=lambda k: 0,
    make_states=lambda problems, bucket: CounterState(jnp.asarray(problems, jnp.int32),
                                                      jnp.zeros(len(problems), bool)),
    step_budget=lambda bucket: 64, parse_problem=_parse,
    outcome=lambda k, state: ({"left": int(state.count)}, int(state.count) == 0),
    defaults=TrainingDefaults(num_demos=8, num_demos_fixed=False, hidden=(8,),
                              tau_in_termination=(False, True, True), num_test=10, iterations=100,
                              learning_rate=3e-2))


COUNTDOWN_JOINT = dataclasses.replace(  # a task whose defaults fix a training mode
    COUNTDOWN, defaults=dataclasses.replace(COUNTDOWN.defaults, training="joint"))


def test_a_task_defined_outside_the_library_demonstrates_and_trains_one_level():
  batch = datasets.training_demos(COUNTDOWN, seed=0, num_demos=6, num_strong=2)
  demos.validate(batch, SPEC)
  assert np.asarray(batch.strong).sum() == 2
  assert [int(n) for n in batch.length] == [2 * k for k in COUNTDOWN.training_problems(0, 6)]
  view = views.lowest_view(batch, SPEC.num_levels)
  config = TrainConfig(iterations=60, eval_every=30, hidden=(8,), root="mlp", root_hidden=8,
                             learning_rate=3e-2, strong_weight=1.0)
  model = objective.LevelModel(networks.make_hierarchy(SPEC, config).levels[2], networks.make_root(SPEC, 2, config))
  progress = levelwise.train_level(model, view, 2, config, fitting.Hooks(log=lambda row: None))
  assert progress.losses[-1][1] < progress.losses[0][1]
  assert evaluation.accuracy(COUNTDOWN, COUNTDOWN.oracle, [1, 3, 5]) == 1.0
  assert tasks.get("tests.test_task_interface:COUNTDOWN") is COUNTDOWN


@pytest.mark.slow
def test_a_task_path_that_does_not_load_or_is_no_task_is_refused_naming_it():
  assert tasks.get("tests.test_task_interface:COUNTDOWN") is COUNTDOWN
  for path, message in [("no_such_module:TASK", "cannot load task 'no_such_module:TASK': ModuleNotFoundError"),
                        ("tests.test_task_interface:NO_SUCH", "cannot load task 'tests.test_task_interface:"
                         "NO_SUCH': AttributeError"),
                        ("tests.test_task_interface:json", "is a module, not a php_jax Task"),
                        ("no_colon", "unknown task 'no_colon'")]:
    with pytest.raises(ValueError, match=message):
      tasks.get(path)


@pytest.mark.slow  # about 40 s; the default suite trains this task in process (above) and refuses bad paths
def test_the_training_command_and_evaluate_run_a_task_given_by_import_path(tmp_path):
  name = "--task=tests.test_task_interface:COUNTDOWN"
  workdir = tmp_path / "run"
  proc = subprocess.run([sys.executable, "-m", "experiments.train", name, f"--workdir={workdir}", "--num_strong=8",
                         "--root=mlp", "--eval_every=50"], capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr[-3000:]
  results = json.loads((workdir / "results.json").read_text())
  assert results["task"] == "tests.test_task_interface:COUNTDOWN" and set(results["levels"]) == {"0", "1", "2"}
  assert results["config"]["iterations"] == 100 and results["config"]["hidden"] == [8]  # the task's defaults
  report = (workdir / "report.html").read_text()  # the training command's report of a task's run
  assert "Call graph" in report and report.count("<svg") == 4 and "the demonstration&#x27;s own call stack" in report
  problems, bad = tmp_path / "in.jsonl", tmp_path / "bad.jsonl"
  problems.write_text('{"count": 3}\n{"count": 1}\n')
  bad.write_text('{"count": 0}\n')
  outs = [tmp_path / "oracle.jsonl", tmp_path / "learned.jsonl", tmp_path / "refused.jsonl"]
  procs = processes.run_all(
      [[sys.executable, "-m", "experiments.evaluate", name, f"--policy={policy}", f"--problems={file}",
        f"--out={out}"] for policy, file, out in [("oracle", problems, outs[0]), (str(workdir), problems, outs[1]),
                                                  ("oracle", bad, outs[2])]],
      capture_output=True, text=True, timeout=300, cwd=ROOT)
  for proc, out in zip(procs[:2], outs):
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [json.loads(line) for line in out.read_text().splitlines()]
    assert set(rows[0]) == {"left", "terminated", "valid", "steps", "correct"}
  assert [json.loads(line) for line in outs[0].read_text().splitlines()] == [
      {"left": 0, "terminated": True, "valid": True, "steps": 6, "correct": True},
      {"left": 0, "terminated": True, "valid": True, "steps": 2, "correct": True}]
  assert procs[2].returncode == 2 and f"{bad}:1:" in procs[2].stderr and not outs[2].exists()


@pytest.mark.slow
def test_a_checkpoint_made_with_other_settings_or_data_is_refused(tmp_path):
  path = str(tmp_path / "checkpoint")
  batch = datasets.training_demos(COUNTDOWN, seed=0, num_demos=4, num_strong=2)
  config = TrainConfig(iterations=2, eval_every=1, hidden=(4,), root="mlp", root_hidden=4)
  levelwise.train_hierarchy(SPEC, batch, config, log=lambda row: None, checkpoint_path=path)
  saved = file_bytes(pathlib.Path(path))
  other_data = datasets.training_demos(COUNTDOWN, seed=1, num_demos=4, num_strong=2)
  for demos_, config_, message in [
      (batch, dataclasses.replace(config, hidden=(5,)), r"hidden: \[4\] there, \[5\] here"),
      (batch, dataclasses.replace(config, seed=1), "seed: 0 there, 1 here"),
      (other_data, config, "demonstrations differ"),
      (batch._replace(strong=np.array([True, False, False, False])), config, "demonstrations differ")]:
    with pytest.raises(checkpoint.CheckpointError, match=message):
      levelwise.train_hierarchy(SPEC, demos_, config_, log=lambda row: None, checkpoint_path=path)
  assert file_bytes(pathlib.Path(path)) == saved


@pytest.mark.slow
def test_a_workdir_made_with_other_settings_is_refused_until_overwrite(tmp_path):
  workdir = tmp_path / "run"
  base = [sys.executable, "-m", "experiments.train", "--task=tests.test_task_interface:COUNTDOWN",
          f"--workdir={workdir}", "--num_strong=2", "--root=mlp", "--iterations=20", "--eval_every=10"]
  first = subprocess.run(base, capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert first.returncode == 0, first.stderr[-3000:]
  before = file_bytes(workdir, but=(run.LOCK_FILE,))  # the lock holds the refused run's pid
  proc = subprocess.run(base + ["--iterations=30"], capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert proc.returncode == 2 and "iterations: 20 there, 30 here" in proc.stderr, proc.stderr[-2000:]
  assert proc.stderr.count("\n") == 1 and "--overwrite" in proc.stderr
  assert file_bytes(workdir, but=(run.LOCK_FILE,)) == before  # nothing written
  again = subprocess.run(base + ["--iterations=30", "--overwrite"], capture_output=True, text=True, timeout=600,
                         cwd=ROOT)
  assert again.returncode == 0, again.stderr[-3000:]
  assert json.loads((workdir / "results.json").read_text())["config"]["iterations"] == 30
  metrics = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  assert sum("capacity" in row for row in metrics) == 3 and not any("resumed" in row for row in metrics)
  as_file = tmp_path / "file"
  as_file.write_text("x")
  proc = subprocess.run(base[:4] + [f"--workdir={as_file}", "--num_strong=2"], capture_output=True, text=True,
                        timeout=600, cwd=ROOT)
  assert proc.returncode == 2 and "is a file" in proc.stderr and as_file.read_text() == "x"


@pytest.mark.slow
def test_sigterm_keeps_the_checkpoint_says_how_to_resume_and_the_rerun_continues_one_record(tmp_path):
  workdir = tmp_path / "run"
  command = [sys.executable, "-m", "experiments.train", "--task=tests.test_task_interface:COUNTDOWN",
             f"--workdir={workdir}", "--num_strong=2", "--root=mlp", "--iterations=1000", "--eval_every=20"]
  proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
  deadline = time.time() + 300
  while not (workdir / "checkpoint" / "state.json").exists() and time.time() < deadline and proc.poll() is None:
    time.sleep(0.1)
  proc.send_signal(signal.SIGTERM)
  stderr = proc.communicate(timeout=120)[1]
  assert proc.returncode == 130 and "Traceback" not in stderr, stderr[-2000:]
  assert stderr.strip().splitlines()[-1].startswith("interrupted:") and "rerun the same command" in stderr
  saved = resume.read_training(str(workdir / "checkpoint"))
  assert saved[0]["level"] == 2 and saved[0]["progress"]["iteration"] >= 20
  assert not leftovers(workdir)
  before = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  rerun = subprocess.run(command, capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert rerun.returncode == 0, rerun.stderr[-3000:]
  rows = [json.loads(line) for line in (workdir / "metrics.jsonl").read_text().splitlines()]
  steps = [(row["level"], row["iteration"]) for row in rows if "iteration" in row]
  assert len(steps) == len(set(steps)) == 3 * 1000 // 20  # every evaluation once, none twice
  assert sum("capacity" in row for row in rows) == 3 and not any("resumed" in row for row in rows)
  seconds = [row["seconds"] for row in rows]
  assert seconds == sorted(seconds) and seconds[-1] >= before[-1]["seconds"]  # the clock went on
  results = json.loads((workdir / "results.json").read_text())
  assert results["wall_seconds"] >= seconds[-1]


def _checkpoint_meta(workdir):
  """The training checkpoint's metadata (level, progress), or None before the first one: its state.json
  (read while the run saves, it is the old one or the new one)."""
  path = workdir / checkpoint.TRAINING_DIR / resume.STATE_FILE
  return json.loads(path.read_text())["states"][0] if path.exists() else None


def _kill_when(command, log, ready, moment, timeout=300):
  """Starts command, polls ready() every few milliseconds while it runs, then SIGKILLs it."""
  with open(log, "w") as stderr:
    proc = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=stderr, cwd=ROOT)
  deadline = time.time() + timeout
  while not ready():
    assert proc.poll() is None, f"the run ended before {moment}: {pathlib.Path(log).read_text()[-2000:]}"
    assert time.time() < deadline, f"no {moment} within {timeout} s"
    time.sleep(0.005)
  proc.kill()
  proc.wait(timeout=60)
  assert proc.returncode == -signal.SIGKILL


@pytest.mark.slow
def test_sigkill_at_any_moment_then_a_rerun_ends_as_an_uninterrupted_run(tmp_path):
  """The same command killed with SIGKILL mid-level, while a finished level decodes its views, at the level
  switch and during the final writes, each time rerun, ends with the bytes and results of a run never killed."""
  def command(workdir):
    return [sys.executable, "-m", "experiments.train", "--task=tests.test_task_interface:COUNTDOWN",
            f"--workdir={workdir}", "--num_strong=2", "--root=mlp", "--iterations=1000", "--eval_every=20"]

  reference = tmp_path / "reference"
  proc = subprocess.run(command(reference), capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr[-3000:]
  workdir = tmp_path / "killed"
  moments = [  # (what the poll waits for, the checkpoint it must have left)
      ("level 2 mid-way", lambda m: m and m["level"] == 2 and m["progress"],
       lambda m: m["level"] == 2 and m["progress"]["iteration"] < 1000),
      ("level 2's last iteration saved, its views decoding", lambda m: m and m["level"] == 2 and m["progress"]
       and m["progress"]["iteration"] == 1000, lambda m: m["level"] == 2 and m["progress"]["iteration"] == 1000),
      ("the switch to level 1, before its first checkpoint", lambda m: m and m["level"] == 1 and not m["progress"],
       lambda m: m["level"] == 1 and m["progress"] is None)]
  for moment, ready, left in moments:
    _kill_when(command(workdir), tmp_path / "stderr", lambda: ready(_checkpoint_meta(workdir)), moment)
    assert left(_checkpoint_meta(workdir)), (moment, _checkpoint_meta(workdir))
  _kill_when(command(workdir), tmp_path / "stderr", (workdir / checkpoint.MODEL_DIR).exists, "the model's write")
  assert _checkpoint_meta(workdir)["level"] == -1 and not (workdir / "results.json").exists()
  # What a kill inside a write leaves beside the files: a partly written temporary file (the target is whole).
  for name in ("results.json", checkpoint.ARCHITECTURE_FILE):
    (workdir / f".{name}.0123456789ab.tmp").write_bytes((reference / name).read_bytes()[:100])
  rerun = subprocess.run(command(workdir), capture_output=True, text=True, timeout=600, cwd=ROOT)
  assert rerun.returncode == 0, rerun.stderr[-3000:]

  assert sorted(p.name for p in workdir.iterdir()) == sorted(p.name for p in reference.iterdir())  # no .tmp left
  assert saved_model(workdir) == saved_model(reference)
  results, expected = (json.loads((d / "results.json").read_text()) for d in (workdir, reference))
  for entry in (*results["levels"].values(), *expected["levels"].values()):
    del entry["seconds"]
  for entry in (results, expected):
    del entry["wall_seconds"], entry["commit"]  # the wall time counts every attempt (below); the checkout's commit
  assert results == expected  # test accuracies, config, per-level losses, snapshots and decoding agreement
  rows, expected_rows = ([json.loads(line) for line in (d / "metrics.jsonl").read_text().splitlines()]
                         for d in (workdir, reference))
  seconds = [row.pop("seconds") for row in rows]
  assert rows == [{k: v for k, v in row.items() if k != "seconds"} for row in expected_rows]  # once each
  assert seconds == sorted(seconds)  # the clock went on across the attempts
  assert json.loads((workdir / "results.json").read_text())["wall_seconds"] >= seconds[-1]


def test_bad_training_settings_are_refused_naming_the_setting(tmp_path):
  for changes, message in [({"learning_rate": float("nan")}, "learning_rate"), ({"iterations": -1}, "iterations"),
                           ({"tau_limit": (0, -1, None)}, "tau_limit"), ({"min_capacity": (0, -2, 3)}, "min_capacity"),
                           ({"root": "gru"}, "root"), ({"hidden": (0,)}, "hidden")]:
    with pytest.raises(ValueError, match=message):
      TrainConfig(**changes)
  with pytest.raises(config_lib.ConfigError, match="min_capacity: needs one value per level"):
    config_lib.check_levels(SPEC, TrainConfig(min_capacity=(0, 9)))
  proc = subprocess.run([sys.executable, "-m", "experiments.train", "--task=tests.test_task_interface:COUNTDOWN",
                         f"--workdir={tmp_path / 'run'}", "--tau_limit=0,x,none"], capture_output=True, text=True,
                        timeout=300, cwd=ROOT)
  assert proc.returncode == 2 and proc.stderr.strip() == "error: --tau_limit must list integers or 'none'; got '0,x,none'"
  assert not (tmp_path / "run").exists()
