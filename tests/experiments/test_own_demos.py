"""Your own demonstrations: the file formats (read, written, refused with file:line), partial annotations,
replay of recorded demonstrations, and the export / fit / decode commands end to end."""
import collections
import dataclasses
import json
import pathlib
import subprocess
import sys

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax import demos
from php_jax.data import call_tree, demo_files, views
from php_jax.demos import UNKNOWN
from php_jax.envs import datasets, replay, tasks
from php_jax.flat import FlatPolicy
from tests import processes

NANOCRAFT = tasks.get("nanocraft")
WAREHOUSE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "warehouse"


def _hierarchy(tmp_path, obj) -> str:
  path = tmp_path / "h.json"
  path.write_text(json.dumps(obj))
  return str(path)


def _demo_file(tmp_path, lines) -> str:
  path = tmp_path / "d.jsonl"
  path.write_text("".join((line if isinstance(line, str) else json.dumps(line)) + "\n" for line in lines))
  return str(path)


SPEC = demo_files.read_hierarchy(str(WAREHOUSE / "warehouse.json")).spec
GOOD = {"observations": [[0.0], [1.0], [2.0]], "actions": [[1], [2]],
        "stack": [[[0, 0], [0, 0], [1, 0]], [[0, 0], [0, 1], [2, 0]]]}


def test_hierarchy_file_read_and_written(tmp_path):
  hierarchy = demo_files.read_hierarchy(_hierarchy(tmp_path, {
      "levels": [["r"], ["a", "b"], ["x"]], "action_sizes": [2, 3], "capacity": [None, 4, 2], "hidden": [16],
      "tau_in_termination": [False, True, True], "tau_limit": [0, None, 2]}))
  assert hierarchy.spec.levels == (("r",), ("a", "b"), ("x",)) and hierarchy.spec.action_sizes == (2, 3)
  assert hierarchy.spec.name == "h" and hierarchy.capacity == (None, 4, 2) and hierarchy.hidden == (16,)
  assert hierarchy.tau_in_termination == (False, True, True) and hierarchy.tau_limit == (0, None, 2)
  demo_files.write_hierarchy(str(tmp_path / "n.json"), NANOCRAFT.spec)
  written = demo_files.read_hierarchy(str(tmp_path / "n.json"))
  assert written.spec == dataclasses.replace(NANOCRAFT.spec, obs_dim=0) and written.tau_limit is None
  bubblesort = tasks.get("bubblesort")  # an exported task's file states the counter settings the task states
  proc = subprocess.run([sys.executable, "-m", "experiments.export_demos", "--task=bubblesort", "--split=test",
                         "--num_demos=2", f"--out={tmp_path / 'b.jsonl'}", f"--hierarchy_out={tmp_path / 'b.json'}"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr
  exported = demo_files.read_hierarchy(str(tmp_path / "b.json"))
  assert (exported.tau_in_termination, exported.tau_limit) == (bubblesort.defaults.tau_in_termination,
                                                               bubblesort.defaults.tau_limit)
  # fit's least capacities: the file's; else, where something is annotated, the annotated calls with room in
  # proportion to the lengths (the warehouse's: 2 and 6 operations, demonstrations up to 1.43 times as long as
  # the longest annotated one: 3, and 8 at most); else none. (In a process of its own: experiments.fit defines
  # its flags on import.)
  check = (f"from experiments import fit; from php_jax.data import demo_files; read = demo_files.read_hierarchy; "
           f"given, plain = read({str(tmp_path / 'h.json')!r}), read({str(WAREHOUSE / 'warehouse.json')!r}); "
           f"demos, _ = demo_files.read_demonstrations({str(WAREHOUSE / 'train.jsonl')!r}, plain.spec); "
           "weak = demos._replace(strong=demos.strong & False); least = lambda h, d: fit.fit_overrides(h, d, False)"
           ".get('min_capacity'); print(least(given, weak), least(plain, demos), least(plain, weak)); "
           "tau = lambda h: [fit.fit_overrides(h, demos, False).get(k) for k in ('tau_in_termination', 'tau_limit')]; "
           "print(tau(given), tau(plain))")
  proc = subprocess.run([sys.executable, "-c", check], capture_output=True, text=True, timeout=300)
  assert proc.stdout.split("\n")[-3:-1] == [
      "(0, 4, 2) (0, 3, 8) None", "[(False, True, True), (0, None, 2)] [(True, True, True), None]"], proc.stderr


@pytest.mark.parametrize("obj, message", [
    ([1], "JSON object"),
    ({"levels": [["r"]], "action_sizes": [2]}, "at least two levels"),
    ({"levels": [["r", "s"], ["a"]], "action_sizes": [2]}, "root level has one procedure"),
    ({"levels": [["r"], ["a", "a"]], "action_sizes": [2]}, "repeats a name"),
    ({"levels": [["r"], ["a"]], "action_sizes": [0]}, "action_sizes"),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "capacity": [1]}, "capacity"),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "hidden": [-1]}, "hidden"),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "tau_in_termination": [1, 0]},
     '"tau_in_termination" must give one true or false per level, root first \\(2\\)'),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "tau_limit": [0]},
     '"tau_limit" must give one integer \\(0 to 4096\\) or null per level'),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "tau_limit": [0, -1]}, "tau_limit"),
    ({"levels": [["r"], ["a"]], "action_sizes": [2], "levles": 1}, "unknown key 'levles'"),
])
def test_bad_hierarchy_files_are_refused_naming_the_file(tmp_path, obj, message):
  path = _hierarchy(tmp_path, obj)
  with pytest.raises(demo_files.DemoFileError, match=message) as error:
    demo_files.read_hierarchy(path)
  assert str(error.value).startswith(path)


def test_demonstrations_read_with_partial_and_missing_stacks(tmp_path):
  partial = {**GOOD, "stack": [None, [[0, 0], None, [-1, -1]]]}
  weak = {k: v for k, v in GOOD.items() if k != "stack"}
  batch, spec = demo_files.read_demonstrations(_demo_file(tmp_path, [GOOD, "", partial, weak]), SPEC)
  assert spec.obs_dim == 1 and batch.length.tolist() == [2, 2, 2] and batch.strong.tolist() == [True, True, False]
  assert batch.procedures[0].tolist() == [[0, 0, 1], [0, 0, 2]] and batch.counters[0, 1].tolist() == [0, 1, 0]
  assert batch.procedures[1].tolist() == [[UNKNOWN] * 3, [0, UNKNOWN, UNKNOWN]]
  assert (batch.procedures[2] == UNKNOWN).all()
  demos.validate(batch, spec)  # partial annotations are valid


@pytest.mark.parametrize("line, message", [
    ("not json", "malformed demonstration"),
    ([], "JSON object"),
    ({**GOOD, "actoins": []}, "unknown key 'actoins'"),
    ({**GOOD, "actions": []}, "non-empty list"),
    ({**GOOD, "actions": [[1], [7]]}, "action 1: factor 0 = 7 is outside 0..3"),
    ({**GOOD, "actions": [[1], [1, 2]]}, "action 1 must be a list of 1 integers"),
    ({**GOOD, "observations": [[0.0], [1.0]]}, "T\\+1 = 3 vectors"),
    ({**GOOD, "observations": [[0.0], [1.0, 2.0], [2.0]]}, "observation 1 has 2 numbers"),
    ({**GOOD, "observations": [[0.0], ["x"], [2.0]]}, "observation 1 must be"),
    ({**GOOD, "stack": [None]}, "one entry per action"),
    ({**GOOD, "stack": [[[0, 0]], None]}, "stack step 0 must list 3"),
    ({**GOOD, "stack": [[[0, 0], [0, 0], [9, 0]], None]}, "procedure id 9 at level 2"),
    ({**GOOD, "stack": [[[0, 0], [0, 0], [1, 1]], None]}, "counters must start at 0"),
    ({**GOOD, "stack": [[[0, 0], [0, 0], [1, 0]], [[0, 0], [0, 2], [2, 0]]]}, "step 1: level 1 goes from"),
    ({**GOOD, "stack": [[[0, 0], [0, 0], [1, 0]], [[0, 0], [0, -1], [2, 0]]]}, "procedure without a counter"),
])
def test_malformed_demonstration_lines_name_file_and_line(tmp_path, line, message):
  path = _demo_file(tmp_path, [GOOD, line])
  with pytest.raises(demo_files.DemoFileError, match=message) as error:
    demo_files.read_demonstrations(path, SPEC)
  assert str(error.value).startswith(f"{path}:2:")


def test_observation_size_must_match_the_spec(tmp_path):
  with pytest.raises(demo_files.DemoFileError, match=r"observations have 1 numbers where the hierarchy's have 6 \(a file of another hierarchy"):
    demo_files.read_demonstrations(_demo_file(tmp_path, [GOOD]), dataclasses.replace(SPEC, obs_dim=6))
  with pytest.raises(demo_files.DemoFileError, match="no demonstrations"):
    demo_files.read_demonstrations(_demo_file(tmp_path, [""]), SPEC)


def test_exported_demonstrations_read_back_unchanged(tmp_path):
  batch = datasets.training_demos(NANOCRAFT, 3, 6, 2)
  path = tmp_path / "out.jsonl"
  demo_files.write_demonstrations(str(path), batch, np.asarray(batch.strong))
  read, spec = demo_files.read_demonstrations(str(path), NANOCRAFT.spec)
  assert spec == NANOCRAFT.spec
  strong = np.asarray(batch.strong)
  np.testing.assert_array_equal(read.strong, strong)
  for name in ("observations", "actions", "length"):
    np.testing.assert_array_equal(getattr(read, name), np.asarray(getattr(batch, name)))
  for name in ("procedures", "counters"):
    np.testing.assert_array_equal(getattr(read, name)[strong], np.asarray(getattr(batch, name))[strong])
    assert (getattr(read, name)[~strong] == UNKNOWN).all()


def test_partial_annotation_is_used_where_the_levels_below_are_known():
  batch = datasets.training_demos(NANOCRAFT, 3, 4, 4)
  procs, taus = np.asarray(batch.procedures).copy(), np.asarray(batch.counters).copy()
  procs[0, 2:, 0] = taus[0, 2:, 0] = UNKNOWN  # demonstration 0: the root's frame partly unknown
  procs[1, 3, 2] = taus[1, 3, 2] = UNKNOWN     # demonstration 1: one lowest-level frame unknown
  partial = batch._replace(procedures=procs, counters=taus)
  demos.validate(partial, NANOCRAFT.spec)
  lowest = views.lowest_view(partial, 3)
  assert lowest.strong.tolist() == [True, True, True, True] and lowest.procedures[1, 3] == UNKNOWN
  level2 = np.asarray(batch.procedures)[..., 2], np.asarray(batch.counters)[..., 2]  # per step = per operation
  above = views.view_above(partial, lowest, 2, *level2)
  assert above.strong.tolist() == [True, False, True, True]  # demonstration 1 has an unknown frame below level 1
  level1 = views.view_above(batch, views.lowest_view(batch, 3), 2, *level2)
  root = views.view_above(partial, above, 1, level1.procedures, level1.counters)
  assert root.strong.tolist() == [True, False, True, True]
  assert root.procedures[0, 0] == 0 and (root.procedures[0, 1:root.length[0]] == UNKNOWN).all()


def test_oracle_replays_its_demonstrations_and_mismatches_are_located():
  batch = datasets.training_demos(NANOCRAFT, 1, 8, 0)
  result = replay.replay(NANOCRAFT.oracle, NANOCRAFT.spec, batch)
  assert result.replayed.all() and (result.first_mismatch == -1).all()
  actions = np.asarray(batch.actions).copy()
  actions[0, 3, 0] = (actions[0, 3, 0] + 1) % 5
  length = np.asarray(batch.length).copy()
  length[1] -= 1  # the hierarchy acts once more than recorded
  changed = batch._replace(actions=jnp.asarray(actions), length=jnp.asarray(length))
  result = replay.replay(NANOCRAFT.oracle, NANOCRAFT.spec, changed)
  assert result.replayed.tolist() == [False, False] + [True] * 6
  assert result.first_mismatch[:2].tolist() == [3, length[1]]
  shuffled = jax.tree.map(lambda x: np.asarray(x)[[2, 0, 3, 4, 1, 5, 6, 7]], changed)
  for chunk in (1, 3):  # chunks of 1, and of 3 with the last padded: each demonstration's own result
    in_chunks = replay.replay(NANOCRAFT.oracle, NANOCRAFT.spec, shuffled, chunk=chunk)
    assert in_chunks.replayed.tolist() == [True, False, True, True, False, True, True, True]
    assert in_chunks.first_mismatch[[1, 4]].tolist() == [3, length[1]]


def test_a_flat_lstm_replays_as_its_own_steps_on_the_recorded_observations_say():
  batch = datasets.training_demos(NANOCRAFT, 1, 6, 0)
  policy = FlatPolicy(NANOCRAFT.spec.obs_dim, NANOCRAFT.spec.action_sizes, 8, rngs=nnx.Rngs(2))
  result = replay.replay(policy, NANOCRAFT.spec, batch)
  for b, length in enumerate(np.asarray(batch.length)):
    carry, previous, expected = policy.initial_carry(), jnp.full(len(policy.action_sizes), -1), -1
    for t in range(length + 1):  # the recorded actions are the LSTM's own up to its first mismatch
      carry, factors, stop = policy.step(carry, jnp.asarray(batch.observations[b, t]), previous)
      taken = [int(jnp.argmax(lp)) for lp in factors]
      if (t < length and (stop > 0 or taken != list(batch.actions[b, t]))) or (t == length and stop <= 0):
        expected = t
        break
      if t < length:
        previous = jnp.asarray(batch.actions[b, t])
    assert result.first_mismatch[b] == expected and result.replayed[b] == (expected == -1), b


def _run(*args):
  return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=600)


@pytest.mark.slow
def test_fit_decode_show_and_report_on_the_warehouse_example(tmp_path):
  workdir, out = tmp_path / "fit", tmp_path / "decoded.jsonl"
  held_out = tmp_path / "held.jsonl"
  held_out.write_text("".join((WAREHOUSE / "held_out.jsonl").read_text().splitlines(keepends=True)[:5]))
  fit = ["experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={WAREHOUSE / 'warehouse.json'}",
         f"--workdir={workdir}", "--iterations=20", "--eval_every=10", "--hidden=16", f"--test={held_out}"]
  proc = _run(*fit)
  assert proc.returncode == 0, proc.stderr
  results_before = (workdir / "results.json").read_bytes()
  results = json.loads(results_before)
  assert results["task"] == "warehouse" and results["num_demos"] == 36 and results["num_held_out"] == 4
  assert results["num_annotated"] + 4 >= 4 and 0 <= results["test"]["held_out_replayed"] <= 1
  report = (workdir / "report.html").read_text()
  assert report.count("<svg") == 4 and "<script" not in report and "Decoded demonstrations" in report
  assert "fulfil" in report and "held_out_replayed" in report
  assert results["test_demos"] == str(held_out) and results["num_test"] == 5
  captions = [part.split("</h3>")[0] for part in report.split("<h3>")[1:]]
  assert len(captions) == 3 and all(f" of {WAREHOUSE / 'train.jsonl'} (" in c for c in captions)  # as numbered there
  shown = [tmp_path / "shown.png", tmp_path / "shown.html"]
  wider, other_actions = tmp_path / "wider.jsonl", tmp_path / "other_actions.jsonl"  # files of other hierarchies
  wider.write_text(json.dumps({"observations": [[0.0] * 7] * 2, "actions": [[0]]}) + "\n")
  other_actions.write_text(json.dumps({"observations": [[0.0] * 6] * 2, "actions": [[5]]}) + "\n")
  decode, show_held_out, show_own, rerun, *refused = processes.run_all([[sys.executable, "-m", *args] for args in [
      ("experiments.decode", f"--policy={workdir}", f"--demos={held_out}", f"--out={out}"),
      ("experiments.show", f"--policy={workdir}", f"--demos={held_out}", "--index=1", f"--out={shown[0]}"),
      ("experiments.show", f"--policy={workdir}", "--index=0", f"--out={shown[1]}"),
      fit,
      ("experiments.decode", f"--policy={workdir}", f"--demos={wider}", f"--out={out}.wider"),
      ("experiments.decode", f"--policy={workdir}", f"--demos={other_actions}", f"--out={out}.other")]],
      capture_output=True, text=True, timeout=600)
  assert all(proc.returncode == 0 for proc in (decode, show_held_out, show_own, rerun)), [
      proc.stderr for proc in (decode, show_held_out, show_own, rerun)]
  assert [proc.stderr for proc in refused] == [
      f"error: {wider}:1: malformed demonstration: observations have 7 numbers where the hierarchy's have 6 (a file "
      "of another hierarchy or environment)\n",
      f"error: {other_actions}:1: malformed demonstration: action 0: factor 0 = 5 is outside 0..3 (the hierarchy's "
      "action factor sizes are [4])\n"]
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  given = [json.loads(line) for line in held_out.read_text().splitlines()]
  assert len(rows) == 5 and "level 1: decoded stacks agree" in decode.stdout
  assert results["test"]["test_replayed"] == sum(row["replayed"] for row in rows) / 5  # decode's replay, the same
  assert "call boundaries: F1" in decode.stdout
  steps = sum(len(json.loads(line)["actions"]) for line in held_out.read_text().splitlines())
  per_step = sum(json.loads(line)["log_likelihood"] for line in out.read_text().splitlines()) / steps
  assert f"log-likelihood: {per_step:.4f} per step" in decode.stdout
  trees = [call_tree.calls(np.asarray(row["stack"])[..., 0], np.asarray(row["stack"])[..., 1]) for row in rows]
  calls = collections.Counter((c.level, c.procedure) for tree in trees for level in call_tree.level_calls(tree)
                              for c in level)
  assert f"level 1 calls: fetch {calls[1, 0]}, deliver {calls[1, 1]}" in decode.stdout
  for row, demo in zip(rows, given):
    assert set(row) == {"log_likelihood", "stack", "replayed", "first_mismatch"}
    assert np.isfinite(row["log_likelihood"]) and row["log_likelihood"] < 0
    assert np.shape(row["stack"]) == (len(demo["actions"]), 3, 2)
    assert row["replayed"] == (row["first_mismatch"] is None)
  assert "the demonstration's own call stack:\n  fulfil\n    fetch\n      go_right: right" in show_held_out.stdout
  assert shown[0].read_bytes()[:8] == b"\x89PNG\r\n\x1a\n" and "<svg" in shown[1].read_text()
  assert f"demonstration 0 of {WAREHOUSE / 'train.jsonl'}" in show_own.stdout  # the run's own file
  # A finished run is not trained again: its results are shown, results.json is left as it was.
  assert json.loads(rerun.stdout.splitlines()[-1]).get("finished_before") is True
  assert (workdir / "results.json").read_bytes() == results_before
  # A demonstration too long for the counter capacities fits no stack: agreement is measured without it.
  long = dict(given[0], stack=None)
  long["observations"] = given[0]["observations"][:1] + given[0]["observations"][1:] * 8
  long["actions"] = given[0]["actions"] * 8
  mixed = tmp_path / "mixed.jsonl"
  mixed.write_text(held_out.read_text() + json.dumps(long) + "\n")
  proc = _run("experiments.decode", f"--policy={workdir}", f"--demos={mixed}", f"--out={tmp_path / 'mixed.out'}")
  assert proc.returncode == 0, proc.stderr
  assert "1 of 6 demonstrations fit no call stack" in proc.stdout
  unfit = json.loads((tmp_path / "mixed.out").read_text().splitlines()[-1])
  assert unfit["log_likelihood"] is None and unfit["stack"] is None
  assert "level 1: decoded stacks agree with the given ones on" in proc.stdout
  assert proc.stdout.count("(over the 5 of 6 demonstrations some stack fits)") == 2  # levels 1 and 2


def test_fit_restarts_each_candidate_by_default_where_one_or_two_demonstrations_are_annotated():
  from php_jax.training import recipe
  assert [recipe.restarts_where_unset(n) for n in (0, 1, 2, 3, 16)] == [1, 2, 2, 1, 1]


@pytest.mark.slow
def test_fit_with_two_annotated_trains_each_candidate_from_two_initialisations(tmp_path):
  lines = [json.loads(line) for line in (WAREHOUSE / "train.jsonl").read_text().splitlines()]
  annotated = [i for i, line in enumerate(lines) if "stack" in line][:2]
  two = _demo_file(tmp_path, [line if i in annotated else {k: v for k, v in line.items() if k != "stack"}
                              for i, line in enumerate(lines)])
  workdir = tmp_path / "fit"
  proc = _run("experiments.fit", f"--demos={two}", f"--hierarchy={WAREHOUSE / 'warehouse.json'}",
              f"--workdir={workdir}", "--training=levelwise", "--iterations=10", "--eval_every=10", "--hidden=8",
              "--noreport")
  assert proc.returncode == 0, proc.stderr[-3000:]
  chosen = json.loads((workdir / "results.json").read_text())["recipe"]
  assert [c["name"] for c in chosen["candidates"]] == ["levelwise", "levelwise-restart1"]
  assert "each is trained from 2 initialisations" in chosen["reasons"]


def test_bad_files_and_flags_end_in_one_line_and_exit_2(tmp_path):
  bad = _demo_file(tmp_path, [GOOD, '{"observations": [[0.0]], "actions": [[1]]}'])
  hierarchy = str(WAREHOUSE / "warehouse.json")
  # fetch is shown calling go_right and pick, which take actions 1 and 2 only: fetch cannot take action 3.
  outside = tmp_path / "outside.jsonl"
  outside.write_text("".join(json.dumps(line) + "\n" for line in [
      GOOD, {"observations": [[0.0], [1.0]], "actions": [[3]], "stack": [[[0, 0], [0, 0], None]]},
      {"observations": [[0.0], [1.0], [2.0]], "actions": [[0], [3]],
       "stack": [[[0, 0], [1, 0], [0, 0]], [[0, 0], [1, 1], [3, 0]]]}]))
  observing = tmp_path / "observing.json"  # the warehouse's hierarchy, each procedure seeing its own entries
  observing.write_text(json.dumps({**json.loads((WAREHOUSE / "warehouse.json").read_text()), "observes": [
      {"fulfil": [0, 1]}, {"fetch": [0, 1], "deliver": [0, 3]}, {"go_left": [0], "go_right": [0, 1]}]}))
  counting = tmp_path / "counting.json"  # the warehouse's hierarchy, one counter limit short
  counting.write_text(json.dumps({**json.loads((WAREHOUSE / "warehouse.json").read_text()), "tau_limit": [0, 1]}))
  fitted = tmp_path / "fitted"  # what segmentation reads first of a fit run's workdir
  fitted.mkdir()
  (fitted / "results.json").write_text(json.dumps({"task": "warehouse", "model": "php", "hierarchy": hierarchy,
                                                   "num_demos": 36, "demos": "train.jsonl"}))
  (fitted / "checkpoint").mkdir()
  cases = [
      (("experiments.segment_errors", f"--run={fitted}"), "is a fit run, whose actions-only demonstrations carry no"),
      (("experiments.fit", f"--demos={outside}", f"--hierarchy={hierarchy}", f"--workdir={tmp_path / 'w1'}",
        "--call_graph=operations"), f"--demos={outside}: demonstration 1, step 0: no chain of calls"),
      (("experiments.fit", f"--demos={outside}", f"--hierarchy={hierarchy}", f"--workdir={tmp_path / 'w2'}",
        "--call_graph=some"), "flag --call_graph=some: value should be one of <all|calls|operations>"),
      (("experiments.fit", f"--demos={bad}", f"--hierarchy={hierarchy}", f"--workdir={tmp_path / 'w3'}"),
       f"{bad}:2:"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={bad}", f"--workdir={tmp_path / 'w4'}"),
       "cannot read a hierarchy"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w5'}", "--validation_fraction=1.5"), "--validation_fraction"),
      (("experiments.decode", f"--policy={tmp_path / 'none'}", f"--demos={bad}", f"--out={tmp_path / 'o.jsonl'}"),
       "no trained model"),
      (("experiments.decode", f"--policy={tmp_path}", f"--demos={bad}", f"--out={bad}"), "is the input file"),
      (("experiments.show", f"--policy={tmp_path / 'none'}"), "no trained model"),
      (("experiments.show", f"--policy={tmp_path}", f"--out={tmp_path / 'o.txt'}"), "must end in .png, .svg, .html"),
      (("experiments.suggest", f"--demos={bad}", "--task=nanocraft", "--budget=1", f"--out={tmp_path / 'o.jsonl'}"),
       "give --demos (with --hierarchy) or --task, one of them"),
      (("experiments.suggest", f"--demos={bad}", f"--hierarchy={hierarchy}", "--budget=1",
        f"--out={tmp_path / 'o.jsonl'}"), f"{bad}:2:"),
      (("experiments.suggest", "--task=nanocraft", "--budget=0", f"--out={tmp_path / 'o.jsonl'}"),
       "flag --budget=0: 0 is not a positive integer"),
      (("experiments.train", "--task=nanocraft", f"--workdir={tmp_path / 'w6'}", f"--annotate={bad}"),
       f"--annotate: {bad}:1: each line needs an \"index\" in 0..63"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w7'}", "--restarts=0"), "flag --restarts=0: 0 is not a positive integer"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w8'}", "--batch_size=-2"),
       "--batch_size: must be a non-negative integer (0: all); got -2"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={observing}",
        f"--workdir={tmp_path / 'w9'}", "--trunk=8"), "--trunk: the hierarchy gives its procedures different"),
      (("experiments.train", "--task=nanocraft", f"--workdir={tmp_path / 'w10'}", "--seeds=1,2",
        "--restarts=2"), "--seeds and --restarts: give one of them"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w11'}", "--memory=gru", "--training=levelwise"),
       "--memory: gru needs joint training"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w12'}", "--env=NoSuchEnv-v0"), "unknown environment 'NoSuchEnv-v0'"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w13'}", "--env=FrozenLake-v1"),
       "the hierarchy does not fit these demonstrations: observation: its fields take 16 numbers"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w14'}", "--model=flat_gru", "--flat_hidden=0"),
       "--flat_hidden must be a positive integer; got 0"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w15'}", "--model=flat_gru", "--restarts=2"),
       "--restarts applies to PHP hierarchies (not --model=flat_gru)"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={counting}",
        f"--workdir={tmp_path / 'w16'}"), f"{counting}: \"tau_limit\" must give one integer (0 to 4096) or null per "
       "level, root first (3); got [0, 1]"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w17'}", "--restarts=3", "--init_seed=2147483000"),
       "--restarts: 3 restarts initialise the last from seed 2147485000, past 2147483647 (a 32-bit seed)"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w18'}", "--strong_warmup=10", "--split_rounds=1"),
       "--strong_warmup: applies to level-wise training only, and --split_rounds=1 to joint training only"),
      (("experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}", f"--hierarchy={hierarchy}",
        f"--workdir={tmp_path / 'w19'}", f"--test={WAREHOUSE / 'train.jsonl'}"),
       f"--test={WAREHOUSE / 'train.jsonl'} is the --demos file: give demonstrations the run does not read"),
      (("experiments.export_demos", "--task=nanocraft", "--split=test", "--size=5", f"--out={tmp_path / 'o.jsonl'}"),
       "--size: nanocraft's problems have no size"),
      (("experiments.export_demos", "--task=bubblesort", "--split=test", "--size=16384", "--num_demos=1",
        f"--out={tmp_path / 'o.jsonl'}"), "--size=16384: its episodes may take 2684141571 steps, beyond 32-bit"),
      (("experiments.export_demos", "--task=nanocraft", "--num_demos=10000000000", f"--out={tmp_path / 'o.jsonl'}"),
       "flag --num_demos=10000000000: 10000000000 is not integer <= 100000"),
      (("experiments.train", "--task=nanocraft", "--num_demos=10000000000", f"--workdir={tmp_path / 'w20'}"),
       "flag --num_demos=10000000000: 10000000000 is not integer <= 100000"),
  ]
  # Run at the same time, each with its own workdir.
  processes.assert_refused(cases)
  assert not any((tmp_path / f"w{i}").exists() for i in range(1, 21)) and not (tmp_path / "o.jsonl").exists()
  assert not (tmp_path / "o.txt").exists()


def test_export_demos_writes_the_training_set_of_train(tmp_path):
  out = tmp_path / "train.jsonl"
  proc = _run("experiments.export_demos", "--task=nanocraft", "--num_demos=6", "--num_strong=2", "--seed=3",
              f"--out={out}", f"--hierarchy_out={tmp_path / 'h.json'}")
  assert proc.returncode == 0, proc.stderr
  hierarchy = demo_files.read_hierarchy(str(tmp_path / "h.json"))
  read, _ = demo_files.read_demonstrations(str(out), hierarchy.spec)
  batch = datasets.training_demos(NANOCRAFT, 3, 6, 2)
  np.testing.assert_array_equal(read.actions, np.asarray(batch.actions))
  np.testing.assert_array_equal(read.strong, np.asarray(batch.strong))


@pytest.mark.slow
def test_train_and_fit_on_its_exported_files_give_the_same_numbers(tmp_path):
  """`fit`, given the files `export_demos` writes for a task, the settings the task states (NanoCraft's: 32
  hidden units) and two of its own choices undone (no least capacity, one initialisation), trains exactly what
  `train --task` trains: the same candidates, chosen by the same recipe, with the same capacities and losses.
  (What validation measures differs: the task's success against held-out replay.)"""
  common = ["--seed=3", "--iterations=10", "--eval_every=5"]
  exports = [["experiments.export_demos", "--task=nanocraft", "--num_demos=6", "--num_strong=2", "--seed=3",
              f"--out={tmp_path / 'train.jsonl'}", f"--hierarchy_out={tmp_path / 'h.json'}"],
             ["experiments.export_demos", "--task=nanocraft", "--split=validation", "--num_demos=4", "--seed=3",
              f"--out={tmp_path / 'validation.jsonl'}"]]
  assert all(_run(*command).returncode == 0 for command in exports)
  train, fit = processes.run_all([[sys.executable, "-m", *command] for command in [
      ["experiments.train", "--task=nanocraft", "--num_demos=6", "--num_strong=2", "--num_validation=4",
       f"--workdir={tmp_path / 'train'}", *common],
      ["experiments.fit", f"--demos={tmp_path / 'train.jsonl'}", f"--hierarchy={tmp_path / 'h.json'}",
       f"--validation={tmp_path / 'validation.jsonl'}", f"--workdir={tmp_path / 'fit'}", "--hidden=32",
       "--tau_in_termination=1,1,1", "--min_capacity=0,0,0", "--restarts=1", *common]]],
      capture_output=True, text=True, timeout=600)
  assert train.returncode == 0 and fit.returncode == 0, train.stderr[-2000:] + fit.stderr[-2000:]

  def numbers(run):
    rows = [json.loads(line) for line in (tmp_path / run / "metrics.jsonl").read_text().splitlines()]
    results = json.loads((tmp_path / run / "results.json").read_text())
    return ([{k: v for k, v in row.items() if k not in ("seconds", "validation")} for row in rows],
            results["recipe"]["candidates"])

  assert [c["name"] for c in numbers("train")[1]] == ["levelwise", "joint"]  # the mode left to the recipe
  assert numbers("train") == numbers("fit")
