"""What a person sees of a run: a demonstration's decoded call stack and posterior (run_view), its picture,
the run's report page, and a finished run that is not trained again. (The commands themselves, end to end:
the slow test in test_own_demos.py; the report in a browser: test_report_browser.py.)"""
import dataclasses
import json
import os
import pathlib
import re
import shutil

import numpy as np
import pytest
from flax import nnx

from experiments.common import pictures, run_report, run_view
from php_jax import flat
from php_jax.analysis import decoding
from php_jax.data import agreement, demo_files, views
from php_jax.demos import UNKNOWN
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint, run, storage
from php_jax.training.config import DISCOVERY_SPLIT_ROUNDS, WEAK_ONLY_ANNEALING, TrainConfig
from tests.saved import file_bytes

LSTM4 = flat.FlatModel("lstm", 4)  # a flat baseline small enough to train in a test

WAREHOUSE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "warehouse"


@pytest.fixture(scope="module")
def fitted(tmp_path_factory):
  """A warehouse 'fit' workdir: an untrained hierarchy saved with results pointing at 5 annotated
  demonstrations, and a metrics log of two levels."""
  workdir = tmp_path_factory.mktemp("fit")
  demos = workdir / "demos.jsonl"
  demos.write_text("".join((WAREHOUSE / "held_out.jsonl").read_text().splitlines(keepends=True)[:5]))
  hierarchy_file = str(WAREHOUSE / "warehouse.json")
  spec = dataclasses.replace(demo_files.read_hierarchy(hierarchy_file).spec, obs_dim=6)
  hierarchy = PHPHierarchy(spec, hidden=(8,), rngs=nnx.Rngs(0))
  checkpoint.save_hierarchy(str(workdir), spec.name, hierarchy, (8,), [1, 8, 8])
  (workdir / run.RESULTS_FILE).write_text(json.dumps({
      "task": "warehouse", "model": "php", "demos": str(demos), "hierarchy": hierarchy_file, "num_demos": 5,
      "config": {"training": "levelwise", "iterations": 10}, "test": {"held_out_replayed": 0.25}}))
  (workdir / run.METRICS_FILE).write_text("".join(json.dumps(row) + "\n" for row in [
      {"level": 2, "capacity": 8, "seconds": 1}, {"level": 2, "iteration": 5, "loss": 3.0, "seconds": 2},
      {"level": 2, "iteration": 10, "loss": 2.0, "seconds": 3},
      {"level": 0, "iteration": 10, "loss": 1.0, "validation": 0.5, "seconds": 4}]))
  return workdir


def test_a_shown_demonstration_is_its_decoded_stack_with_names_and_a_posterior_per_level(fitted):
  view = run_view.load(str(fitted))
  batch, source = run_view.demonstrations(view, None)
  assert source.endswith("demos.jsonl") and len(batch.length) == 5
  (drawn, lines), = run_view.decoded(view, batch, [3])
  decoded = decoding.decode(view.hierarchy, view.capacity, batch)
  n = int(batch.length[3])
  assert drawn["decoded"].end == n and drawn["actions"][0] in ("left", "right", "pick", "drop")
  lowest = [c for c in drawn["decoded"].callees for c in c.callees]
  assert [c.procedure for c in lowest] == [int(decoded.procedures[3, c.start, 2]) for c in lowest]
  for level, marginal in enumerate(drawn["marginals"]):  # each step's procedures: a distribution
    np.testing.assert_allclose(marginal[:n].sum(-1), 1.0, atol=1e-4)
    assert marginal.shape[1] == view.hierarchy.spec.num_procs(level)
  assert lines[0].startswith("decoded call stack (log-likelihood ") and lines[1] == "  fulfil"
  assert "the demonstration's own call stack:" in lines and set(drawn["agreement"]) == {1, 2}
  for level in (1, 2):  # frames per step, and where calls start, which frames alone do not show
    given = batch.procedures[3, :n], batch.counters[3, :n]
    truth = agreement.boundary_steps(agreement.call_starts(*given, level))
    found = agreement.boundary_steps(agreement.call_starts(decoded.procedures[3, :n], decoded.counters[3, :n],
                                                           level))
    scores = agreement.boundary_scores([truth], [found])
    assert (f"level {level}: frames (procedure, counter) agree on {drawn['agreement'][level]:.3f} of the annotated "
            f"steps; call boundaries: {len(truth & found)} of {len(truth)} found, {len(found)} decoded "
            f"(F1 {scores['f1']:.3f})") in lines
  figure = run_view.figure(view, drawn, "demonstration 3")
  assert pictures.save(figure, "x.png", "t")[:4] == b"\x89PNG"
  assert pictures.save(figure, "x.html", "t", "\n".join(lines)).decode().count("<svg") == 1


def test_the_report_holds_settings_results_curves_call_graph_and_three_drawn_demonstrations(fitted):
  path = run_report.write(str(fitted))
  page = pathlib.Path(path).read_text()
  assert page.count("<svg") == 4 and "<script" not in page and " src=" not in page
  assert "held_out_replayed" in page and "0.250" in page and "Learning curves" in page
  assert page.count("<td>fetch</td>") == 1 and "<td>any</td>" in page  # the call graph, every procedure once
  assert page.count("<h3>demonstration ") == 3
  assert run_report.write_if_stale(str(fitted)) is None  # newer than results.json: left as it is
  os.utime(path, (0, 0))
  assert run_report.write_if_stale(str(fitted)) == path


def test_a_joint_runs_split_search_is_reported_round_by_round(fitted, tmp_path):
  workdir = tmp_path / "joint"
  shutil.copytree(fitted, workdir)
  results = json.loads((workdir / run.RESULTS_FILE).read_text())
  rounds = [{"round": 0, "kept": "level 2: 3 becomes a copy of 1 for caller 0", "log_likelihood_per_step": -0.0381,
             "candidates": [["unchanged", -0.3], ["level 2: 3 becomes a copy of 1 for caller 0", -0.0381]]},
            {"round": 1, "kept": "unchanged", "log_likelihood_per_step": -0.0004, "candidates": [["unchanged", -0.0004]]}]
  (workdir / run.RESULTS_FILE).write_text(json.dumps({**results, "joint": {"split_search": rounds}}))
  page = pathlib.Path(run_report.write(str(workdir))).read_text()
  assert "<h2>Split search</h2>" in page and "<td>level 2: 3 becomes a copy of 1 for caller 0</td><td>-0.038</td>" in page
  assert "<td>2</td><td>unchanged</td>" in page
  (workdir / run.RESULTS_FILE).write_text(json.dumps({**results, "joint": {"seconds": 1.0}}))
  assert "Split search" not in pathlib.Path(run_report.write(str(workdir))).read_text()


def test_a_flat_lstm_is_refused_by_show_and_reported_without_stacks(tmp_path):
  workdir = str(tmp_path / "flat")
  experiment = _flat_experiment()
  run.train_and_evaluate(experiment, TrainConfig(iterations=2, eval_every=1), workdir, flat_model=LSTM4,
                         echo=lambda row: None)
  with pytest.raises(ValueError, match="holds a flat baseline, which has no call stack to show"):
    run_view.load(workdir)
  page = pathlib.Path(run_report.write(workdir)).read_text()
  assert "No call stack to show" in page and page.count("<svg") == 1 and "flat LSTM</text>" in page


def test_a_finished_run_is_not_trained_again_and_other_settings_are_named(tmp_path):
  workdir, experiment, config = str(tmp_path / "flat"), _flat_experiment(), TrainConfig(iterations=2, eval_every=1)
  rows = []
  first = run.train_and_evaluate(experiment, config, workdir, flat_model=LSTM4, echo=rows.append)
  files = file_bytes(tmp_path / "flat")
  rows.clear()
  again = run.train_and_evaluate(experiment, config, workdir, flat_model=LSTM4, echo=rows.append)
  assert again == json.loads(json.dumps(first))  # as results.json holds it
  assert rows == [{"test": first["test"], "wall_seconds": first["wall_seconds"], "finished_before": True}]
  assert file_bytes(tmp_path / "flat") == files
  results_path = tmp_path / "flat" / run.RESULTS_FILE
  older = json.loads(results_path.read_text())
  del older["config"]["length_buckets"]  # a run made before that setting existed ran with its default
  older["config"]["batch_size"] = None  # recorded unset before runs resolved it: the full batch, as 0 is now
  results_path.write_text(json.dumps(older))
  assert run.train_and_evaluate(experiment, config, workdir, flat_model=LSTM4, echo=rows.append) == older
  with pytest.raises(run.WorkdirError, match=r"other settings \(--iterations: 2 there, 3 here\); use a fresh"):
    run.train_and_evaluate(experiment, dataclasses.replace(config, iterations=3), workdir, flat_model=LSTM4)
  with pytest.raises(run.WorkdirError, match=r"--flat_hidden: 4 there, 5 here"):
    run.train_and_evaluate(experiment, config, workdir, flat_model=flat.FlatModel("lstm", 5))


def test_a_finished_php_run_records_its_resolved_settings_and_is_not_trained_again(tmp_path):
  """The settings that follow the demonstrations (the strong weight; the annealing, segmentation and
  split search of a joint run none of whose demonstrations is annotated) are recorded as resolved, so that
  the same command finds its run finished."""
  flat = _flat_experiment()
  demos = flat.demos._replace(procedures=np.full_like(flat.demos.procedures, UNKNOWN),
                              counters=np.full_like(flat.demos.counters, UNKNOWN),
                              strong=np.zeros_like(flat.demos.strong))
  experiment = run.Experiment("warehouse", flat.spec, demos, validate=flat.validate, test=flat.test,
                              extra=flat.extra)
  workdir = str(tmp_path / "weak")
  config = TrainConfig(iterations=2, eval_every=1, hidden=(4,), training="joint", split_iterations=2,
                       split_hint_iterations=0, length_buckets=1)
  first = run.train_and_evaluate(experiment, config, workdir, echo=lambda row: None)
  assert first["config"]["anneal_temperature"] == WEAK_ONLY_ANNEALING
  assert (first["config"]["segment_iterations"], first["config"]["split_rounds"]) == (1, DISCOVERY_SPLIT_ROUNDS)
  assert 1 <= len(first["joint"]["split_search"]) <= DISCOVERY_SPLIT_ROUNDS
  rows = []
  run.train_and_evaluate(experiment, config, workdir, echo=rows.append)
  assert rows == [{"test": first["test"], "wall_seconds": first["wall_seconds"], "finished_before": True}]


def _flat_experiment() -> run.Experiment:
  spec = demo_files.read_hierarchy(str(WAREHOUSE / "warehouse.json")).spec
  demos, spec = demo_files.read_demonstrations(str(WAREHOUSE / "held_out.jsonl"), spec)
  demos = type(demos)(*(np.asarray(x)[:4] for x in demos))
  return run.Experiment("warehouse", spec, demos, validate=lambda model: 0.5, test=lambda model: {"replayed": 0.5},
                        extra={"num_demos": 4})


def test_a_model_or_run_that_cannot_be_read_is_refused_not_reported(fitted, tmp_path):
  """Hostile workdirs (a model.json edited, even signed anew; no results; a metrics row of strings) are
  refused in one ValueError naming the file."""
  bad = tmp_path / "bad"
  shutil.copytree(fitted, bad)
  (bad / run.REPORT_FILE).unlink(missing_ok=True)  # an earlier test's
  architecture = json.loads((bad / checkpoint.ARCHITECTURE_FILE).read_text())
  for capacity in ([8], [0, 0, 0], ["a", "b", "c"], [11, 10_000_000, 8]):
    (bad / checkpoint.ARCHITECTURE_FILE).write_text(json.dumps({**architecture, "capacity": capacity}))
    with pytest.raises(checkpoint.CheckpointError, match='"capacity" must give one integer in 1..4096 per level'):
      checkpoint.saved_capacity(str(bad))
  spec = {**architecture["spec"], "obs_dim": -1}
  edited = storage.signed({**{k: v for k, v in architecture.items() if k != "sha256"}, "spec": spec})
  (bad / checkpoint.ARCHITECTURE_FILE).write_text(json.dumps(edited))  # signed anew, as an editor could
  with pytest.raises(checkpoint.CheckpointError, match="malformed hierarchy spec"):
    checkpoint.load_policy(str(bad))
  with pytest.raises(ValueError, match="malformed hierarchy spec"):
    run_report.write(str(bad))  # a report of a model that cannot be read is refused, not written
  assert not (bad / run.REPORT_FILE).exists()
  empty = tmp_path / "empty"
  empty.mkdir()
  with pytest.raises(ValueError, match="not a finished run's results"):
    run_report.write(str(empty))
  rows = tmp_path / "rows"
  shutil.copytree(fitted, rows)
  (rows / run.METRICS_FILE).write_text('{"level": 2, "iteration": "ten", "loss": 1.0}\n')
  with pytest.raises(ValueError, match=r"metrics.jsonl:1: not a metrics row"):
    run_report.write(str(rows))


def test_a_run_whose_task_is_not_its_models_hierarchy_is_refused(fitted, tmp_path):
  other = tmp_path / "other"
  shutil.copytree(fitted, other)
  (other / run.RESULTS_FILE).write_text(json.dumps({"task": "bubblesort", "seed": 0, "num_demos": 128,
                                                    "num_strong": 0, "config": {}, "test": {}}))
  with pytest.raises(ValueError, match="its model is not a hierarchy of task 'bubblesort'"):
    run_view.demonstrations(run_view.load(str(other)), None)


def test_a_report_given_the_drawn_demonstrations_and_their_numbers_is_the_one_that_reads_the_file(fitted, tmp_path):
  workdir = tmp_path / "given"
  shutil.copytree(fitted, workdir)
  read_again = pathlib.Path(run_report.write(str(workdir))).read_text()
  batch, _ = run_view.demonstrations(run_view.load(str(workdir)), None)
  drawn = run_report.drawn_demonstrations(batch)
  given = views.select(batch, drawn)
  page = pathlib.Path(run_report.write(str(workdir), given, drawn)).read_text()
  assert _drawn(page) == _drawn(read_again) and len(_drawn(page)) == 6
  assert f"<h3>demonstration {drawn[0]} of {_results_demos(workdir)} (" in page


def _drawn(page: str) -> list[str]:
  """The captions and call trees of the demonstrations a report draws."""
  return re.findall(r"<h3>.*?</h3>|<pre>.*?</pre>", page, re.S)


def _results_demos(workdir) -> str:
  return json.loads((workdir / run.RESULTS_FILE).read_text())["demos"]
