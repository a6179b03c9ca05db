"""Faults injected into every command: SIGKILL at seeded random moments, then the same command again, ends as
an uninterrupted run would (train, fit, sweep; evaluate, export_demos, decode and show write whole files or
none); a full disk (a real tmpfs where the tests run as root, else a patched write) ends in one line and a
rerun that loses and repeats nothing."""
import errno
import json
import os
import pathlib
import random
import re
import shutil
import subprocess
import sys
import time

import pytest

from php_jax.data import files
from php_jax.envs import datasets
from php_jax.training import run
from php_jax.training import config as config_lib
from tests.saved import leftovers, saved_model
from tests.test_task_interface import COUNTDOWN

ROOT = pathlib.Path(__file__).resolve().parents[2]
WAREHOUSE = ROOT / "examples" / "warehouse"
# Random SIGKILL moments per command: train and fit are killed twice per attempt, the others once.
MOMENTS = int(os.environ.get("PHP_JAX_KILL_MOMENTS", "6"))


def _train(workdir):
  return ["experiments.train", "--task=tests.test_task_interface:COUNTDOWN", f"--workdir={workdir}",
          "--num_strong=2", "--root=mlp", "--iterations=200", "--eval_every=20"]


def _fit(workdir):
  return ["experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={WAREHOUSE / 'warehouse.json'}",
          f"--workdir={workdir}", "--iterations=60", "--eval_every=20", "--hidden=16", "--seed=1"]


def _evaluate(out):
  return ["experiments.evaluate", "--task=addition", "--policy=oracle",
          f"--problems={ROOT / 'examples' / 'addition.jsonl'}", f"--out={out}"]


def _export(out):
  return ["experiments.export_demos", "--task=nanocraft", "--num_demos=12", "--num_strong=3", "--seed=2",
          f"--out={out}", f"--hierarchy_out={out}.hierarchy.json"]


def _sweep(workdir):
  return ["experiments.sweep", "--task=tests.test_task_interface:COUNTDOWN", f"--workdir={workdir}",
          "--grid=num_strong=1,2", "--", "--root=mlp", "--iterations=100", "--eval_every=20", "--noreport"]


def _python(args, timeout=600):
  return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=timeout, cwd=ROOT)


def _kill_after(args, seconds):
  """Starts the command and SIGKILLs it after `seconds` (if it has not ended by then)."""
  proc = subprocess.Popen([sys.executable, "-m", *args], stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL,
                          cwd=ROOT)
  try:
    proc.wait(timeout=seconds)
  except subprocess.TimeoutExpired:
    proc.kill()
    proc.wait()


def _timed(args) -> float:
  start = time.time()
  proc = _python(args)
  assert proc.returncode == 0, proc.stderr[-3000:]
  return time.time() - start


def _run_record(workdir: pathlib.Path) -> dict:
  """What must not depend on faults: the saved model (`tests.saved.saved_model`), results.json less its times,
  metrics less times."""
  results = json.loads((workdir / "results.json").read_text())
  for key in ("wall_seconds", "commit"):
    del results[key]
  for entry in [*results.get("levels", {}).values(), results.get("joint", {})]:
    entry.pop("seconds", None)
  for score in results.get("recipe", {}).get("scores", []):
    del score["wall_seconds"]
  rows = [json.loads(line) for line in (workdir / run.METRICS_FILE).read_text().splitlines()]
  return {"model": saved_model(workdir), "results": results,
          "metrics": [{k: v for k, v in row.items() if k != "seconds"} for row in rows]}


@pytest.mark.slow
@pytest.mark.parametrize("command", [_train, _fit], ids=["train", "fit"])
def test_training_killed_at_random_moments_then_rerun_ends_as_uninterrupted(tmp_path, command):
  reference = tmp_path / "reference"
  duration = _timed(command(reference))
  rng = random.Random(0)
  for attempt in range(MOMENTS // 2):
    workdir = tmp_path / f"killed{attempt}"
    for _ in range(2):  # killed twice at random moments, then run to the end
      _kill_after(command(workdir), rng.uniform(0.0, duration))
    proc = _python(command(workdir))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert _run_record(workdir) == _run_record(reference), attempt
    assert not leftovers(workdir)


@pytest.mark.slow
@pytest.mark.parametrize("command", [_evaluate, _export], ids=["evaluate", "export_demos"])
def test_outputs_killed_at_random_moments_are_whole_or_absent_and_the_rerun_writes_them(tmp_path, command):
  reference = tmp_path / "reference.jsonl"
  duration = _timed(command(reference))
  rng = random.Random(1)
  for attempt in range(MOMENTS):
    out = tmp_path / f"killed{attempt}.jsonl"
    _kill_after(command(out), rng.uniform(0.0, duration))
    assert not out.exists() or out.read_bytes() == reference.read_bytes()  # never part of one
    proc = _python(command(out))
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert out.read_bytes() == reference.read_bytes()


@pytest.mark.slow
def test_a_sweep_killed_at_random_moments_leaves_no_run_behind_and_its_rerun_ends_as_uninterrupted(tmp_path):
  reference = tmp_path / "reference"
  duration = _timed(_sweep(reference))
  runs = sorted(p.name for p in reference.iterdir())
  assert runs == ["num_strong=1", "num_strong=2"]
  rng = random.Random(2)
  for attempt in range(MOMENTS):
    workdir = tmp_path / f"killed{attempt}"
    _kill_after(_sweep(workdir), rng.uniform(0.0, duration))
    time.sleep(1)  # the run it was running ends on the SIGTERM its parent's death sends
    proc = _python(_sweep(workdir))
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    for name in runs:
      assert _run_record(workdir / name) == _run_record(reference / name), (attempt, name)


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
  workdir = tmp_path_factory.mktemp("fitted") / "fit"
  proc = _python(_fit(workdir) + ["--noreport"])
  assert proc.returncode == 0, proc.stderr[-3000:]
  return workdir


def _decode(policy, out):
  return ["experiments.decode", f"--policy={policy}", f"--demos={WAREHOUSE / 'held_out.jsonl'}", f"--out={out}"]


def _show(policy, out):
  return ["experiments.show", f"--policy={policy}", "--index=3", f"--out={out}"]


@pytest.mark.slow
@pytest.mark.parametrize("command, suffix", [(_decode, ".jsonl"), (_show, ".png")], ids=["decode", "show"])
def test_decode_and_show_killed_at_random_moments_write_whole_files_or_none(tmp_path, fitted, command, suffix):
  reference = tmp_path / f"reference{suffix}"
  duration = _timed(command(fitted, reference))
  rng = random.Random(3)
  for attempt in range(MOMENTS):
    out = tmp_path / f"killed{attempt}{suffix}"
    _kill_after(command(fitted, out), rng.uniform(0.0, duration))
    assert not out.exists() or out.read_bytes() == reference.read_bytes()  # never part of one
    assert _python(command(fitted, out)).returncode == 0
    assert out.read_bytes() == reference.read_bytes()


@pytest.mark.slow
def test_a_full_disk_ends_the_run_and_the_rerun_repeats_no_row(tmp_path, monkeypatch):
  """The third checkpoint write fails with ENOSPC: the run ends with that OSError, having kept what it had;
  the rerun resumes and ends with every metrics row once, as an uninterrupted run."""
  demos = datasets.training_demos(COUNTDOWN, seed=0, num_demos=6, num_strong=2)
  config = config_lib.TrainConfig(iterations=40, eval_every=10, hidden=(8,), root="mlp", root_hidden=8,
                                  learning_rate=3e-2)
  experiment = run.Experiment("tests.test_task_interface:COUNTDOWN", COUNTDOWN.spec, demos,
                              validate=lambda model: 1.0, test=lambda model: {}, extra={})
  run.train_and_evaluate(experiment, config, str(tmp_path / "reference"))
  writes, real = [], files.os.replace

  def replace(source, target):
    writes.append(target)
    if len(writes) == 3:
      raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), target)
    real(source, target)

  monkeypatch.setattr(files.os, "replace", replace)
  with pytest.raises(OSError, match="No space left"):
    run.train_and_evaluate(experiment, config, str(tmp_path / "full"))
  monkeypatch.setattr(files.os, "replace", real)
  assert not leftovers(tmp_path / "full")
  run.train_and_evaluate(experiment, config, str(tmp_path / "full"))
  ours, expected = _run_record(tmp_path / "full"), _run_record(tmp_path / "reference")
  assert [r for r in ours["metrics"] if "resumed" not in r] == expected["metrics"]
  assert ours["model"] == expected["model"] and ours["results"] == expected["results"]


@pytest.fixture(scope="module")
def small_filesystem(tmp_path_factory):
  """Mounts a tmpfs (root on Linux only) and yields a function that sets its size in KiB."""
  mount = tmp_path_factory.mktemp("tmpfs")
  if os.geteuid() != 0 or subprocess.run(["mount", "-t", "tmpfs", "-o", "size=4k", "tmpfs", str(mount)],
                                         capture_output=True).returncode != 0:
    pytest.skip("mounting a tmpfs needs root and the right to mount")
  try:
    yield mount, lambda kib: subprocess.run(["mount", "-o", f"remount,size={kib}k", str(mount)], check=True)
  finally:
    subprocess.run(["umount", str(mount)], check=False)


@pytest.mark.slow
def test_a_real_full_disk_ends_in_one_line_and_the_rerun_ends_as_uninterrupted(tmp_path, small_filesystem):
  """The training command on a tmpfs too small for its run, at sizes that fill it at different moments (the first
  checkpoint, a later one, the final writes): one line naming the workdir or the file in it, exit 2, nothing
  half-written; with the space given back, the rerun ends as an uninterrupted run, every metrics row once."""
  mount, resize = small_filesystem
  reference = tmp_path / "reference"
  _timed(_train(reference))
  for kib in (64, 128, 232):  # Orbax's files take 4 KiB each on a tmpfs
    workdir = mount / "run"
    resize(kib)
    proc = _python(_train(workdir))
    assert proc.returncode == 2 and re.fullmatch(rf"error: {re.escape(str(workdir))}(/\S+)?: No space left on device",
                                                 proc.stderr.strip()), (kib, proc.stderr[-2000:])
    assert not leftovers(workdir), kib
    resize(1024)
    proc = _python(_train(workdir))
    assert proc.returncode == 0, (kib, proc.stderr[-3000:])
    ours, expected = _run_record(workdir), _run_record(reference)
    assert [r for r in ours["metrics"] if "resumed" not in r] == expected["metrics"], kib
    assert ours["model"] == expected["model"] and ours["results"] == expected["results"], kib
    shutil.rmtree(workdir)
