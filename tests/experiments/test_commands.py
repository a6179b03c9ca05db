"""The runnable example and the benchmark commands work (functionality only; nothing here is timed)."""
import importlib.util
import json
import os
import pathlib
import subprocess
import sys

import pytest

from tests import processes

ROOT = pathlib.Path(__file__).resolve().parents[2]


def test_embedding_example_learns_and_decodes(capsys):
  spec = importlib.util.spec_from_file_location("embed_estep", ROOT / "examples" / "embed_estep.py")
  example = importlib.util.module_from_spec(spec)
  spec.loader.exec_module(example)
  first, last, agreement = example.main(steps=80)
  assert last < first - 1.0
  assert agreement == 1.0  # Viterbi recovers the planted segmentation: every step's procedure and counter
  assert "decoded procedure:" in capsys.readouterr().out


@pytest.mark.slow
def test_benchmark_commands_run_and_cross_check(tmp_path):
  out = tmp_path / "estep.json"
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "estep", "--sizes=4x12x2x3,2x5x1x4",
                         "--min_time=0", f"--out={out}"], capture_output=True, text=True, timeout=300, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr
  assert "4x12x2x3" in proc.stdout and out.exists()
  rows = __import__("json").loads(out.read_text())
  assert all(r["max_rel_loglik_diff"] < 1e-5 for r in rows)
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "rollout", "--task=addition", "--size=5", "--problems=3",
                         "--min_time=0"], capture_output=True, text=True, timeout=300, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr
  assert "steps/s" in proc.stdout
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "train_step", "--task=nanocraft", "--hidden=8", "--root=mlp",
                         "--min_time=0"], capture_output=True, text=True, timeout=300, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr
  assert "networks only" in proc.stdout and "of the full loss" in proc.stdout


@pytest.mark.slow
def test_many_demos_benchmark_fits_each_number_of_copies(tmp_path):
  out = tmp_path / "many.json"
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "many_demos",
                         f"--demos={ROOT / 'examples' / 'warehouse' / 'train.jsonl'}",
                         f"--hierarchy={ROOT / 'examples' / 'warehouse' / 'warehouse.json'}", "--copies=1,8",
                         "--iterations=200", f"--out={out}"], capture_output=True, text=True, timeout=900, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr[-3000:]
  rows = json.loads(out.read_text())
  assert [r["demonstrations"] for r in rows] == [40, 320]
  assert [r["batch_size"] for r in rows] == [36, 64]  # all 36 in training; 288, above 256: the default minibatch
  assert all(r["peak_gb"] > 0 and r["s_per_update"] > 0 and r["steps_per_s"] > 0 for r in rows)


@pytest.mark.slow
def test_fast_path_benchmark_times_a_users_demonstrations(tmp_path):
  out = tmp_path / "fast.json"
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "fast_path",
                         f"--demos={ROOT / 'examples' / 'warehouse' / 'train.jsonl'}",
                         f"--hierarchy={ROOT / 'examples' / 'warehouse' / 'warehouse.json'}", "--batch_size=4",
                         "--hidden=8", "--min_time=0", f"--out={out}"], capture_output=True, text=True, timeout=900,
                        cwd=ROOT)
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert "40 demonstrations of" in proc.stdout and "today's)" in proc.stdout
  rows = json.loads(out.read_text())
  assert len(rows) == 5 and rows[0]["speedup"] == 1.0 and all(r["ms"] > 0 for r in rows)


def test_benchmark_refuses_bad_commands_flags_and_files_in_one_line(tmp_path):
  warehouse = ROOT / "examples" / "warehouse"
  user_files = [f"--demos={warehouse / 'train.jsonl'}", f"--hierarchy={warehouse / 'warehouse.json'}"]
  (tmp_path / "bad.jsonl").write_text("{not json\n")
  processes.assert_refused([
      (["experiments.benchmark", "nonsense"], "usage: python -m experiments.benchmark {estep|"),
      (["experiments.benchmark", "estep", "--min_time=x"], "--min_time"),
      (["experiments.benchmark", "rollout", "--task=nonsense"], "--task: "),
      (["experiments.benchmark", "many_demos", *user_files, "--copies=1,ten"],
       "--copies must list positive integers; got 1,ten"),
      (["experiments.benchmark", "fast_path", f"--demos={tmp_path / 'bad.jsonl'}", user_files[1]], "bad.jsonl"),
      (["experiments.benchmark", "fast_path", "--demos=/nonexistent.jsonl", user_files[1]], "/nonexistent.jsonl"),
      (["experiments.benchmark", "estep", f"--out={tmp_path / 'missing' / 'out.json'}"], "does not exist"),
  ], timeout=300)


@pytest.mark.slow
def test_scaling_benchmark_runs_on_four_devices(tmp_path):
  out = tmp_path / "scaling.json"
  proc = subprocess.run([sys.executable, "-m", "experiments.benchmark", "scaling", "--task=nanocraft", "--num_demos=6",
                         "--hidden=8", "--root=mlp", "--seeds=2", "--min_time=0", f"--out={out}"],
                        capture_output=True, text=True, timeout=900, cwd=ROOT,
                        env={**os.environ, "XLA_FLAGS": "--xla_force_host_platform_device_count=4"})
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert "x 4;" in proc.stdout and "vmapped vs in turn" in proc.stdout
  rows = json.loads(out.read_text())
  assert [r["what"].split(" (")[0] for r in rows[:4]] == ["level 2 loss", "level 1 loss", "level 0 loss", "joint loss"]
  assert all(r["all_devices_s"] > 0 for r in rows[:4]) and all(r["vmapped_s"] > 0 for r in rows[4:])
