"""A run's workdir: one run at a time (its lock), and a metrics log with every row once whatever was killed when."""
import json
import os
import signal
import subprocess
import sys
import threading
import time

import pytest

from php_jax.training import checkpoint, run

HOLD = """
import sys, time
from php_jax.training import checkpoint, run
with run.workdir_lock(sys.argv[1]):
  print("held", flush=True)
  time.sleep(60)
"""


def _holder(workdir):
  proc = subprocess.Popen([sys.executable, "-c", HOLD, str(workdir)], stdout=subprocess.PIPE, text=True)
  assert proc.stdout.readline().strip() == "held"
  return proc


def test_a_second_run_is_refused_naming_the_holder_and_a_killed_one_blocks_nothing(tmp_path):
  holder = _holder(tmp_path / "w")
  try:
    with pytest.raises(run.WorkdirError, match=rf"in use by another run \(pid {holder.pid}\)"):
      with run.workdir_lock(str(tmp_path / "w")):
        pass
  finally:
    os.kill(holder.pid, signal.SIGKILL)
    holder.wait()
  with run.workdir_lock(str(tmp_path / "w")):  # the kernel released the killed run's lock
    assert (tmp_path / "w" / run.LOCK_FILE).read_text() == str(os.getpid())
  assert not (tmp_path / "w" / run.LOCK_FILE).exists()  # a run that ends leaves no lock file behind


def test_waiting_takes_the_lock_once_the_holder_ends(tmp_path):
  holder = _holder(tmp_path / "w")
  subprocess.Popen(["sh", "-c", f"sleep 1; kill {holder.pid}"])
  with run.workdir_lock(str(tmp_path / "w"), wait=True):
    assert holder.wait() == -signal.SIGTERM
    assert (tmp_path / "w" / run.LOCK_FILE).read_text() == str(os.getpid())


def test_a_run_waiting_on_a_removed_lock_file_takes_the_new_one(tmp_path):
  """A run waiting on the lock file of one that ends (and removes it) takes the lock on a file at the path,
  so that a run after it sees it held."""
  workdir = str(tmp_path / "w")
  order = []
  with run.workdir_lock(workdir):
    waiting = threading.Thread(target=lambda: _take(workdir, order, "second"))
    waiting.start()
    time.sleep(0.5)  # the second now waits on the first's file
  waiting.join(10)
  with run.workdir_lock(workdir):  # the third
    order.append("third")
  assert order == ["second", "third"] and not (tmp_path / "w" / run.LOCK_FILE).exists()


def _take(workdir, order, name):
  with run.workdir_lock(workdir, wait=True):
    with pytest.raises(run.WorkdirError, match="in use by another run"):
      with run.workdir_lock(workdir):
        pass
    order.append(name)


def test_a_workdir_that_is_a_file_is_refused(tmp_path):
  (tmp_path / "f").write_text("")
  with pytest.raises(run.WorkdirError, match="is a file, not a directory"):
    with run.workdir_lock(str(tmp_path / "f")):
      pass


def test_metrics_start_afresh_unless_resumed(tmp_path, capsys):
  path = tmp_path / run.METRICS_FILE
  path.write_text('{"level": 2, "seconds": 1.0}\n{"level": 2, "iteration": 10, "seconds": 2.0}\n')
  with run.MetricsLog(str(tmp_path)) as log:  # killed before its first checkpoint: nothing to resume
    log({"level": 2})
  assert [json.loads(line)["level"] for line in path.read_text().splitlines()] == [2]
  path.write_text('{"a": 1, "seconds": 1.0}\n{"b": 2, "seconds": 5.0}\n{"c": 3, "seconds": 9.0}\n')
  with run.MetricsLog(str(tmp_path)) as log:  # the checkpoint was taken after two rows
    log({"resumed": True, "logged": 2})
    log({"d": 4})
  rows = [json.loads(line) for line in path.read_text().splitlines()]
  assert [list(row)[0] for row in rows] == ["a", "b", "d"] and rows[-1]["seconds"] >= 5.0


def test_a_workdir_saved_before_orbax_is_refused_until_overwrite(tmp_path):
  (tmp_path / "checkpoint.msgpack").write_bytes(b"old")
  (tmp_path / "model.msgpack").write_bytes(b"old")
  (tmp_path / "model.json").write_text("{}")
  older = r"model.msgpack was saved by an older php_jax; use a fresh workdir, or --overwrite"
  with pytest.raises(run.WorkdirError, match=older):
    run.clear_workdir(str(tmp_path), run.RUN_FILES)
  with pytest.raises(checkpoint.CheckpointError, match="model.msgpack was saved by an older php_jax; train"):
    checkpoint.load_policy(str(tmp_path))
  run.clear_workdir(str(tmp_path), run.RUN_FILES, overwrite=True)
  assert sorted(os.listdir(tmp_path)) == []
