"""The flat baselines (LSTM, GRU), the sweep runner's grid, the plot command and the segmentation report."""
import collections
import json
import re
import subprocess
import sys
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from experiments import plot, segment_errors, sweep
from php_jax import fitting, flat
from php_jax.analysis import decoding
from php_jax.data import views
from php_jax.envs import datasets, evaluation, nanocraft, nanocraft_task, tasks
from php_jax.training import checkpoint, networks
from tests import processes
from php_jax.training.config import TrainConfig

NANOCRAFT = tasks.get("nanocraft")


def _demos(num=8, seed=3):
  problems = nanocraft_task.random_problems(seed, num)
  return problems, datasets.oracle_demonstrations(NANOCRAFT, nanocraft_task.make_states(problems), 0,
                                                  nanocraft.ORACLE_STEP_BUDGET)


@pytest.mark.parametrize("cell", flat.CELLS)
def test_flat_log_likelihood_matches_stepping_by_hand(cell):
  _, demos = _demos(2)
  policy = flat.FlatPolicy(5, (5,), 16, cell=cell, rngs=nnx.Rngs(0))
  obs, actions, n = demos.observations[0], demos.actions[0], int(demos.length[0])
  carry, expected, previous = policy.initial_carry(), 0.0, jnp.array([-1])
  for t in range(n + 1):
    carry, factors, stop = policy.step(carry, jnp.asarray(obs[t]), previous)
    if t < n:
      expected += float(factors[0][actions[t, 0]] + jax.nn.log_sigmoid(-stop))
      previous = jnp.asarray(actions[t])
    else:
      expected += float(jax.nn.log_sigmoid(stop))
  got = policy.log_likelihood(jnp.asarray(obs), jnp.asarray(actions), jnp.asarray(n))
  np.testing.assert_allclose(got, expected, rtol=1e-5)


@pytest.mark.parametrize("cell", flat.CELLS)
def test_flat_baseline_clones_its_training_demonstrations_and_survives_saving(tmp_path, cell):
  problems, demos = _demos(8)
  policy = flat.FlatPolicy(5, (5,), 32, cell=cell, rngs=nnx.Rngs(1))
  report = flat.train(policy, demos, fitting.Schedule(400, 1e-2, 100), fitting.Hooks(log=lambda r: None))
  assert report["losses"][-1][1] < 0.05 * report["losses"][0][1]
  outcomes = evaluation.solve(NANOCRAFT, policy, problems)
  assert np.mean([o["correct"] for o in outcomes]) >= 0.75  # its own training problems
  checkpoint.save_flat(str(tmp_path), "nanocraft", policy, NANOCRAFT.spec)
  name, loaded = checkpoint.load_policy(str(tmp_path))
  assert name == "nanocraft" and isinstance(loaded, flat.FlatPolicy) and loaded.cell_kind == cell
  assert evaluation.solve(NANOCRAFT, loaded, problems) == outcomes
  loaded.sample = True  # drawn with the evaluation's keys: the same draws each time
  assert evaluation.solve(NANOCRAFT, loaded, problems) == evaluation.solve(NANOCRAFT, loaded, problems)


def test_a_sampling_flat_lstm_draws_its_actions_and_stop_from_their_distributions():
  policy = flat.FlatPolicy(5, (2, 3), 4, rngs=nnx.Rngs(0))
  factors = [jnp.log(jnp.array([0.3, 0.7])), jnp.log(jnp.array([0.5, 0.1, 0.4]))]
  stop_logit = jnp.log(0.2 / 0.8)
  action, stop = policy.decide(factors, stop_logit, jax.random.key(0))
  assert action.tolist() == [1, 0] and not stop  # the most likely of each
  policy.sample = True
  actions, stops = jax.vmap(lambda k: policy.decide(factors, stop_logit, k))(jax.random.split(jax.random.key(1),
                                                                                               20_000))
  np.testing.assert_allclose(np.bincount(actions[:, 0], minlength=2) / 20_000, [0.3, 0.7], atol=0.015)
  np.testing.assert_allclose(np.bincount(actions[:, 1], minlength=3) / 20_000, [0.5, 0.1, 0.4], atol=0.015)
  assert abs(float(np.mean(stops)) - 0.2) < 0.015


def test_sweep_grid_is_the_product_without_impossible_combinations():
  combos = sweep.parse_grid(["num_demos=16,64", "num_strong=1,32", "seed=1"])
  assert combos == [{"num_demos": "16", "num_strong": "1", "seed": "1"},
                    {"num_demos": "64", "num_strong": "1", "seed": "1"},
                    {"num_demos": "64", "num_strong": "32", "seed": "1"}]
  assert sweep.run_name(combos[0]) == "num_demos=16,num_strong=1,seed=1"
  lists = sweep.parse_grid(["tau_in_termination=1,1,1|1,0,1", "seed=1,2"])
  assert [c["tau_in_termination"] for c in lists] == ["1,1,1", "1,1,1", "1,0,1", "1,0,1"]
  assert sweep.run_name(lists[2]) == "tau_in_termination=1:0:1,seed=1"
  with pytest.raises(ValueError, match="name=value"):
    sweep.parse_grid(["num_demos"])


def test_sweep_skips_combinations_whose_runs_are_done(tmp_path):
  combos = sweep.parse_grid(["num_strong=1,2"])
  for done in ("num_strong=1/results.json", "num_strong=2/seed=1/results.json"):
    (tmp_path / done).parent.mkdir(parents=True)
    (tmp_path / done).write_text("{}")
  assert [c for _, c in sweep.pending(combos, str(tmp_path), None)] == [{"num_strong": "2"}]
  assert [c for _, c in sweep.pending(combos, str(tmp_path), ["1", "2"])] == combos  # seed=2 missing in both
  (tmp_path / "num_strong=2/seed=2").mkdir()
  (tmp_path / "num_strong=2/seed=2/results.json").write_text("{}")
  assert sweep.pending(combos, str(tmp_path), ["1", "2"]) == [(str(tmp_path / "num_strong=1"), {"num_strong": "1"})]


def test_sweep_runs_each_job_on_one_gpu_parallel_at_a_time_on_each():
  lock, running, seen = threading.Lock(), collections.Counter(), []

  def run(job, device):
    with lock:
      running[device] += 1
      seen.append((job, device, running[device]))
    time.sleep(0.02)
    with lock:
      running[device] -= 1
    return job * 10

  assert list(sweep.run_on_devices(list(range(12)), run, ["0", "1", "3"], parallel=2)) == [j * 10 for j in range(12)]
  assert sorted(j for j, _, _ in seen) == list(range(12))
  assert {d for _, d, _ in seen} == {"0", "1", "3"} and max(n for _, _, n in seen) == 2
  seen.clear()
  list(sweep.run_on_devices(list(range(4)), run, [None], parallel=3))  # no --gpus: this process's devices
  assert {d for _, d, _ in seen} == {None} and max(n for _, _, n in seen) <= 3


def test_sweep_run_sees_only_its_gpu_without_preallocation(tmp_path, monkeypatch):
  envs = []
  monkeypatch.setattr(sweep.subprocess, "run", lambda command, env, **kwargs: envs.append(env) or
                      subprocess.CompletedProcess(command, 0))
  monkeypatch.setenv("CUDA_VISIBLE_DEVICES", "0,1,2,3")
  monkeypatch.delenv("XLA_PYTHON_CLIENT_PREALLOCATE", raising=False)
  assert sweep._run("nanocraft", str(tmp_path / "a"), {"seed": "1"}, [], "2") == (str(tmp_path / "a"), 0, None)
  sweep._run("nanocraft", str(tmp_path / "b"), {"seed": "2"}, [], None)
  assert envs[0]["CUDA_VISIBLE_DEVICES"] == "2" and envs[0]["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
  assert envs[1]["CUDA_VISIBLE_DEVICES"] == "0,1,2,3" and "XLA_PYTHON_CLIENT_PREALLOCATE" not in envs[1]


def test_plot_draws_the_figure_and_tables(tmp_path):
  runs = tmp_path / "runs"
  for i, (model, total, strong, acc) in enumerate([("php", 16, 1, 0.5), ("php", 16, 1, 0.7), ("php", 16, 4, 1.0),
                                                   ("php", 16, 0, 0.3), ("flat_lstm", 16, 0, 0.2)]):
    (runs / str(i)).mkdir(parents=True)
    levels = {"1": {"decoding_agreement": acc / 2, "relabelled_agreement": acc}} if model == "php" else {}
    (runs / str(i) / "results.json").write_text(json.dumps(
        {"task": "nanocraft", "model": model, "num_demos": total, "num_strong": strong, "test": {"accuracy": acc},
         "levels": levels}))
  (runs / "graph").mkdir()
  (runs / "graph" / "results.json").write_text(json.dumps(
      {"task": "nanocraft", "model": "php", "num_demos": 16, "num_strong": 4, "test": {"accuracy": 0.9},
       "config": {"training": "joint", "call_graph": "operations"}}))
  for seed, accs in enumerate([(1.0, 1.0), (1.0, 0.99)]):
    (runs / f"add{seed}").mkdir()
    (runs / f"add{seed}" / "results.json").write_text(json.dumps(
        {"task": "addition", "num_demos": 160, "num_strong": 3, "test": {"500": accs[0], "1000": accs[1]}}))
  out = tmp_path / "out"
  proc = subprocess.run([sys.executable, "-m", "experiments.plot", f"--runs={runs}", f"--out={out}"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-2000:]
  table = (out / "nanocraft.md").read_text()
  assert "| php | 16 | 1 | 2 | 0.600 (0.500–0.700, 0/2) | 0.300, 0.600 |" in table
  assert "| php | 16 | 0 | 1 | 0.300 (0.300–0.300, 0/1) |" in table  # weak only
  assert "| flat_lstm | 16 | 0 | 1 | 0.200 (0.200–0.200, 0/1) | – |" in table
  assert "| php-joint-operations | 16 | 4 | 1 | 0.900 (0.900–0.900, 0/1) | – |" in table  # a line of its own
  assert "| php | 160 | 3 | 2 | 1.000 (1.000–1.000, 2/2) | 0.995 (0.990–1.000, 1/2) | – |" in (
      out / "addition.md").read_text()  # test sets by increasing length
  for png in ("nanocraft.png", "addition.png"):
    assert (out / png).read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
  assert plot.read_table(str(out / "nanocraft.md")) == plot.summarise(plot.group_runs(plot.load_results([str(runs)]))[
      "nanocraft"])  # a table reads back as the rows it was written from (to 3 decimals: these are)
  redrawn = tmp_path / "redrawn"
  proc = subprocess.run([sys.executable, "-m", "experiments.plot", f"--tables={out / 'addition.md'}",
                         f"--out={redrawn}", "--against=test_size"], capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-2000:]
  assert sorted(p.name for p in redrawn.iterdir()) == ["addition.png"]  # the table is not rewritten
  empty = subprocess.run([sys.executable, "-m", "experiments.plot", f"--runs={tmp_path / 'none'}",
                          f"--out={out}"], capture_output=True, text=True, timeout=300)
  assert empty.returncode == 2 and "no results.json" in empty.stderr


def test_segmentation_classifies_splits_merges_and_mistaken_procedures():
  procs, taus = np.array([0, 0, 0, 1]), np.array([0, 1, 2, 0])
  assert segment_errors.classify(procs, taus, procs, taus) == ("correct", [])
  assert segment_errors.classify(procs, taus, procs, np.array([0, 1, 0, 0])) == ("split", [2])
  assert segment_errors.classify(np.array([0, 0, 1]), np.array([0, 0, 0]), np.array([0, 0, 1]),
                               np.array([0, 1, 0])) == ("merge", [1])
  assert segment_errors.classify(procs, taus, np.array([0, 0, 0, 2]), taus)[0] == "other"
  nothing = np.zeros(0, int)  # no path of the levels below explains the demonstration
  assert segment_errors.classify(nothing, nothing, nothing, nothing) == ("other", [])


def test_segmentation_report_finds_a_split_in_the_supervisors_level_1_view():
  demos = datasets.training_demos(tasks.get("nanocraft"), seed=2, num_demos=6, num_strong=2)
  spec = NANOCRAFT.spec

  def truth(view, level):  # the supervisor's frames at each of the view's operations
    steps = np.arange(6)[:, None], np.maximum(view.times, 0), level
    return np.asarray(demos.procedures)[steps], np.asarray(demos.counters)[steps]

  view = views.lowest_view(demos, spec.num_levels)
  view = views.view_above(demos, view, 2, *truth(view, 2))
  procs, taus = truth(view, 1)
  report = segment_errors.level_report(demos, view, 1, procs, taus, spec.levels[1])
  assert report == {"kinds": {"correct": 4}, "where": {}, "wrong": []}
  weak = int(np.flatnonzero(~demos.strong)[0])
  second = int(np.flatnonzero(taus[weak] == 1)[0])  # a call's second operation, pushed anew
  taus = taus.copy()
  taus[weak, second] = 0
  report = segment_errors.level_report(demos, view, 1, procs, taus, spec.levels[1])
  assert report["kinds"] == {"correct": 3, "split": 1}
  assert report["where"] == {f"split in {spec.levels[1][procs[weak, second]]}": 1}
  assert report["wrong"][0]["demo"] == weak


def test_segmentation_of_a_joint_run_reads_the_whole_stack_decoding_at_every_level(tmp_path, monkeypatch, capsys):
  """A joint run's segmentation is the trained hierarchy's whole-stack decoding, read at each level's own
  operations: a decoding equal to the supervisor's stacks is reported correct on every weak demonstration."""
  demos = datasets.training_demos(NANOCRAFT, seed=2, num_demos=6, num_strong=2)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, TrainConfig(hidden=(4,)))
  checkpoint.save_hierarchy(str(tmp_path), "nanocraft", hierarchy, (4,), capacity=[8, 6, 4])
  (tmp_path / "checkpoint").mkdir()  # joint runs read no decoded views from it
  (tmp_path / "results.json").write_text(json.dumps({"task": "nanocraft", "seed": 2, "num_demos": 6, "num_strong": 2,
                                                     "config": {"training": "joint"}}))
  supervisor = decoding.Decoded(np.zeros(6), np.asarray(demos.procedures), np.asarray(demos.counters))
  monkeypatch.setattr(decoding, "decode", lambda h, capacity, batch: supervisor)
  segment_errors.report(str(tmp_path), None, 3)
  rows = [json.loads(line) for line in capsys.readouterr().out.splitlines()]
  assert rows == [{"level": 2, "kinds": {"correct": 4}, "where": {}}, {"level": 1, "kinds": {"correct": 4}, "where": {}}]
  procedures = np.asarray(demos.procedures).copy()
  weak = int(np.flatnonzero(~demos.strong)[0])
  procedures[weak, 0, 1] = 1 - procedures[weak, 0, 1]  # the first level-1 procedure of one weak demonstration
  monkeypatch.setattr(decoding, "decode", lambda h, capacity, batch: supervisor._replace(procedures=procedures))
  segment_errors.report(str(tmp_path), 1, 3)
  assert json.loads(capsys.readouterr().out.splitlines()[0])["kinds"] == {"correct": 3, "other": 1}
  checkpoint.save_hierarchy(str(tmp_path), "nanocraft", hierarchy, (4,))  # without its counter capacities
  with pytest.raises(ValueError, match="records no counter capacities"):
    segment_errors.report(str(tmp_path), None, 3)


@pytest.mark.parametrize("entries, message", [
    (["num_demos"], "name=value"), (["=1,2"], "name=value"), (["seed="], "name=value"),
    (["seed=1", "seed=2"], "given twice"), (["workdir=a"], "the sweep's own"), (["seed=1,,2"], "empty value"),
    (["num_demos=16,x"], "non-negative integers"), (["num_strong=-1"], "non-negative integers"),
])
def test_sweep_refuses_bad_grids(entries, message):
  with pytest.raises(ValueError, match=message):
    sweep.parse_grid(entries)


def test_sweep_command_refuses_bad_flags_and_writes_nothing(tmp_path):
  cases = [(["--grid=num_demos=16,x"], "num_demos values"), (["--parallel=0"], "parallel"),
           (["--grid=seed=1", "--grid=seed=2"], "given twice"), (["--gpus=0,0"], "distinct"),
           (["--seeds=1,x"], "distinct non-negative integers"), (["--seeds=1,2", "--grid=seed=3"], "give one of them"),
           (["--task=sorting"], "--task: unknown task 'sorting'"), (["--workdir="], "--workdir: must name a directory"),
           (["--grid=seed=1,2", "--", "--seed=5"], "--seed=5 after --: the sweep sets --seed itself"),
           (["--grid=seed=1", "--", f"--workdir={tmp_path / 'elsewhere'}"], "the sweep sets --workdir itself"),
           (["--seeds=1,2", "--", "--seed=3"], "--seed=3 after --: the sweep sets --seed itself"),
           (["--gpus="], "GPU ids must be distinct and non-empty"), (["--parallel=100000000000000000000"], "parallel")]
  # Run at the same time, each with its own workdir.
  processes.assert_refused([(["experiments.sweep", "--task=nanocraft", f"--workdir={tmp_path / f'sweep{i}'}", *flags],
                             message) for i, (flags, message) in enumerate(cases)], timeout=300)
  assert list(tmp_path.iterdir()) == []


@pytest.mark.slow
def test_a_sweep_whose_every_run_is_refused_ends_in_one_line_and_leaves_no_workdir(tmp_path):
  workdir = tmp_path / "sweep"
  proc = subprocess.run([sys.executable, "-m", "experiments.sweep", "--task=nanocraft", f"--workdir={workdir}",
                         "--grid=seed=1", "--", "--hidden="], capture_output=True, text=True, timeout=300)
  assert proc.returncode == 2 and "seed=1: error: --hidden must list integers" in proc.stdout, proc.stdout
  assert proc.stderr.strip() == ("error: every run was refused; the first: --hidden must list integers; got ''")
  assert not workdir.exists()  # neither the refused run's workdir nor the sweep's


def test_plot_names_a_corrupt_results_file(tmp_path):
  for name, text in [("truncated", '{"task": "nanocraft", "te'), ("list", "[1]"), ("no_test", '{"task": "x"}'),
                     ("accuracy", '{"task": "x", "num_strong": 1, "test": {"accuracy": "high"}}'),
                     ("no_strong", '{"task": "x", "test": {"accuracy": 1.0}}')]:
    (tmp_path / name).mkdir()
    (tmp_path / name / "results.json").write_text(text)
    with pytest.raises(ValueError, match=f"{tmp_path / name / 'results.json'}: not a training run's results"):
      plot.load_results([str(tmp_path / name)])
  (tmp_path / "bytes").mkdir()
  (tmp_path / "bytes" / "results.json").write_bytes(b'{"task": "\xff"}')
  out = tmp_path / "out"
  proc = subprocess.run([sys.executable, "-m", "experiments.plot", f"--runs={tmp_path / 'bytes'}", f"--out={out}"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
  assert f"{tmp_path / 'bytes' / 'results.json'}: not a training run's results" in proc.stderr
  assert not out.exists()


def test_plot_refuses_a_table_it_did_not_write(tmp_path):
  header = ("| model | demonstrations | strong | trials | accuracy: mean (min–max, trials at 1.0) | "
            "level-1 agreement: exact, renamed |\n| --- | --- | --- | --- | --- | --- |\n")
  for text, where in [("| a | b |\n", ":1: not a table"), (header + "| php | 64 | x | 5 | 0.5 (0.1–0.9) | – |\n", ":3: "),
                      (header + "| php | 64 | 4 | 5 | 0.5 (0.6–0.9) | – |\n", ":3: cell '0.5 (0.6–0.9)': needs"),
                      (header + "| php | 64 | 4 | 5 | high | – |\n", ":3: cell 'high' is not"),
                      (header + "| php | 64 | 4 | 5 |\n", ":3: 4 cells, the header has 6")]:
    (tmp_path / "t.md").write_text(text)
    with pytest.raises(ValueError, match=re.escape(f"{tmp_path / 't.md'}{where}")):
      plot.read_table(str(tmp_path / "t.md"))
  (tmp_path / "t.md").write_text(header + "| php | 64 | 4 | 5 | 0.500 (0.100–0.900) | 0.9, 0.9 |\n")
  assert plot.read_table(str(tmp_path / "t.md")) == {
      ("php", 64, 4): plot.Row(5, {"accuracy": plot.Accuracy(0.5, 0.1, 0.9, None, 5)}, "0.9, 0.9")}
  cases = [([f"--tables={tmp_path / 't.md'}", f"--runs={tmp_path}"], "either --runs"), ([], "either"),
           ([f"--tables={tmp_path / 't.md'}", "--against=test_size"], "test sets named by their size")]
  processes.assert_refused([(["experiments.plot", f"--out={tmp_path / 'out'}", *args], message)
                            for args, message in cases], timeout=300)
  assert not (tmp_path / "out").exists()


@pytest.fixture
def read_only(tmp_path):
  """A folder on a read-only file system (a tmpfs mounted read-only; skipped where mounting is not allowed)."""
  folder = tmp_path / "read_only"
  folder.mkdir()
  if subprocess.run(["mount", "-t", "tmpfs", "-o", "ro", "tmpfs", str(folder)], capture_output=True).returncode:
    pytest.skip("mounting a read-only file system needs root")
  yield folder
  subprocess.run(["umount", str(folder)], check=True)


def test_sweep_and_plot_refuse_a_folder_they_cannot_write_in_one_line(tmp_path):
  (tmp_path / "run").mkdir()
  (tmp_path / "run" / "results.json").write_text(json.dumps({"task": "x", "num_strong": 1, "test": {"accuracy": 1.0}}))
  (tmp_path / "file").write_text("")
  blocked = tmp_path / "file" / "below"
  processes.assert_refused([
      (["experiments.sweep", "--task=nanocraft", f"--workdir={blocked}", "--grid=seed=1"],
       f"error: --workdir={blocked}: cannot write there: Not a directory"),
      (["experiments.plot", f"--runs={tmp_path / 'run'}", f"--out={blocked}"],
       f"error: --out={blocked}: cannot write there: Not a directory")], timeout=300)


def test_sweep_and_plot_refuse_a_read_only_file_system_in_one_line(tmp_path, read_only):
  (tmp_path / "run").mkdir()
  (tmp_path / "run" / "results.json").write_text(json.dumps({"task": "x", "num_strong": 1, "test": {"accuracy": 1.0}}))
  processes.assert_refused([
      (["experiments.sweep", "--task=nanocraft", f"--workdir={read_only / 'sweep'}", "--grid=seed=1"],
       f"error: --workdir={read_only / 'sweep'}: cannot write there: Read-only file system"),
      (["experiments.plot", f"--runs={tmp_path / 'run'}", f"--out={read_only}"],
       f"error: --out={read_only}: cannot write there: Read-only file system")], timeout=300)


def test_segmentation_refuses_bad_runs_and_levels(tmp_path):
  run = tmp_path / "run"
  with pytest.raises(ValueError, match="results.json does not exist"):
    segment_errors.report(str(run), None, 3)
  run.mkdir()
  (run / "checkpoint").mkdir()
  (run / "checkpoint" / "state.json").write_text("not JSON")
  good = {"task": "nanocraft", "seed": 1, "num_demos": 4, "num_strong": 1}
  for results, message in [('{"task": "nanocr', "results.json: not a training run's results"),
                           ({**good, "seed": "1"}, "needs int 'seed'"), ({**good, "task": "nope"}, "unknown task"),
                           ({**good, "model": "flat_lstm"}, "no hierarchy to decode")]:
    (run / "results.json").write_text(results if isinstance(results, str) else json.dumps(results))
    with pytest.raises(ValueError, match=message):
      segment_errors.report(str(run), None, 3)
  (run / "results.json").write_text(json.dumps(good))
  for level in (0, 3):
    with pytest.raises(ValueError, match=r"--level must be in 1..2 for nanocraft"):
      segment_errors.report(str(run), level, 3)
  with pytest.raises(checkpoint.CheckpointError, match="state.json: corrupt or truncated JSON"):
    segment_errors.report(str(run), 1, 3)
  (run / "checkpoint" / "state.json").write_text(json.dumps({"meta": "{}"}))
  with pytest.raises(checkpoint.CheckpointError, match="state.json: not a training checkpoint"):
    segment_errors.report(str(run), 1, 3)
  proc = subprocess.run([sys.executable, "-m", "experiments.segment_errors", f"--run={run}", "--level=7"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 2 and proc.stderr.strip() == "error: --level must be in 1..2 for nanocraft; got 7"
