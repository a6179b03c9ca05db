"""Level views, the EG loss, decoding agreement, checkpoints, and end-to-end training."""
import dataclasses
import json
import shutil

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax import fitting
from php_jax.data import agreement, views
from php_jax.envs import addition, addition_task, datasets, evaluation, nanocraft, nanocraft_task, tasks
from php_jax.inference import lattice
from php_jax.model import PHPLevel, RootMLP
from php_jax.training import checkpoint, levelwise, networks, objective, resume, storage
from php_jax.training.config import TrainConfig

ADDITION = tasks.get("addition")
NANOCRAFT = tasks.get("nanocraft")


def _addition_demos(problems, num_strong):
  return datasets.oracle_demonstrations(ADDITION, addition_task.make_states(problems), num_strong,
                                        addition.oracle_step_budget(max(len(a) for a, _ in problems)))


def test_level_views_are_the_supervisors_call_sequences():
  demos = _addition_demos([("5", "7"), ("12", "34")], num_strong=2)
  lowest = views.lowest_view(demos, 3)
  assert lowest.length.tolist() == [int(n) for n in demos.length]
  level1 = views.view_above(demos, lowest, 2, lowest.procedures, lowest.counters)
  names = ADDITION.spec.levels[2]
  # 5 + 7: write, carry, lshift, then the carry column: write, lshift.
  assert [names[a] for a in level1.actions[0, :level1.length[0], 0]] == ["write", "carry", "lshift", "write",
                                                                         "lshift"]
  assert level1.counters[0, :5].tolist() == [0, 1, 2, 0, 1]
  level0 = views.view_above(demos, level1, 1, level1.procedures, level1.counters)
  assert level0.length.tolist() == [2, 2] and np.all(level0.actions[:, :2, 0] == 0)
  assert level0.counters[0, :2].tolist() == [0, 1]
  # Observations are those at each call's start, then the final one.
  np.testing.assert_array_equal(level0.observations[0, 0], np.asarray(demos.observations[0, 0]))
  np.testing.assert_array_equal(level0.observations[0, 2], np.asarray(demos.observations[0, demos.length[0]]))


def test_level_loss_is_the_complete_data_log_likelihood_for_strong_views():
  demos = _addition_demos([("19", "25"), ("7", "8")], num_strong=2)
  view = views.lowest_view(demos, 3)
  # The lowest level's networks alone, with make_hierarchy's settings for it (it would build all three
  # levels), and the computations jitted: run eagerly, each op compiles on its own.
  php = PHPLevel(ADDITION.spec.num_procs(2), ADDITION.spec.obs_dim, ADDITION.spec.op_sizes(2), (16,),
                 rngs=nnx.Rngs(0))
  model = objective.LevelModel(php, RootMLP(44, 3, (8,), rngs=nnx.Rngs(0)))
  level_loss = nnx.jit(lambda m, buckets: objective.level_loss(m, buckets, 4, strong_weight=1.0))
  batch = views.device_view(view)
  loss = level_loss(model, [batch])
  split = level_loss(model, [views.device_view(b) for b in views.length_buckets(view, 2)])
  np.testing.assert_allclose(split, loss, rtol=1e-6)
  lattice_inputs = nnx.jit(lambda m, one: objective.lattice_inputs(m, one, 4))
  direct = []
  for b in range(2):
    none = -jnp.ones_like(batch.procedures[b])
    one = jax.tree.map(lambda x: x[b], batch)._replace(procedures=none, counters=none)
    inputs = lattice_inputs(model, one)
    direct.append(lattice.complete_log_likelihood(inputs, batch.procedures[b], batch.counters[b]))
  np.testing.assert_allclose(loss, -np.mean(direct), rtol=1e-5)


def test_decoding_agreement_is_one_for_the_truth_and_lower_otherwise():
  demos = _addition_demos([("19", "25"), ("7", "8")], num_strong=0)
  view = views.lowest_view(demos, 3)
  truth = (np.asarray(demos.procedures)[:, :, 2], np.asarray(demos.counters)[:, :, 2])
  assert agreement.agreement(demos, view, 2, *truth) == 1.0
  wrong = (truth[0], np.zeros_like(truth[1]))
  assert agreement.agreement(demos, view, 2, *wrong) < 1.0


def test_relabelled_agreement_ignores_procedure_ids_but_not_segmentation():
  demos = _addition_demos([("19", "25"), ("7", "8"), ("5", "6")], num_strong=0)
  view = views.lowest_view(demos, 3)
  procs, taus = np.asarray(demos.procedures)[:, :, 2], np.asarray(demos.counters)[:, :, 2]
  renamed = np.array([2, 0, 1])[procs]  # write, carry, lshift under other ids
  assert agreement.agreement(demos, view, 2, renamed, taus) < 0.5
  assert agreement.relabelled_agreement(demos, view, 2, renamed, taus) == 1.0
  merged = np.zeros_like(procs)  # every call decoded as one procedure: no renaming recovers the three
  counts, total = agreement.agreement_counts(demos, view, 2, merged, taus)
  assert agreement.relabelled_agreement(demos, view, 2, merged, taus) == counts.max() / total < 1.0
  assert agreement.relabelled_agreement(demos, view, 2, procs + 6, taus) == 1.0  # ids 6..8 of 9, renamed


def test_level_capacity_is_the_longest_annotated_call_at_least_the_minimum():
  demos = _addition_demos([("19", "25"), ("7", "8")], num_strong=1)
  view = views.lowest_view(demos, 3)
  assert levelwise.level_capacity(view, 2, TrainConfig()) == 4  # lshift's four moves
  assert levelwise.level_capacity(view, 2, TrainConfig(min_capacity=(0, 0, 6))) == 6
  assert levelwise.level_capacity(view, 2, TrainConfig(min_capacity=(0, 0, 2))) == 4
  assert levelwise.level_capacity(view, 0, TrainConfig(min_capacity=(50, 0, 0))) == int(view.length.max())


def test_training_refuses_malformed_demonstrations():
  demos = _addition_demos([("19", "25")], num_strong=1)
  counters = np.array(demos.counters)
  counters[0, 3, 2] += 2
  with pytest.raises(ValueError, match="demonstration 0, step 3"):
    levelwise.train_hierarchy(ADDITION.spec, demos._replace(counters=counters), TrainConfig(iterations=1))


def test_checkpoint_round_trip(tmp_path):
  config = TrainConfig(hidden=(16,), tau_in_termination=(True, False, True), seed=3)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, config)
  checkpoint.save_hierarchy(str(tmp_path), "nanocraft", hierarchy, config.hidden)
  name, loaded = checkpoint.load_policy(str(tmp_path))
  assert name == "nanocraft" and loaded.levels[1].tau_in_termination is False
  for a, b in zip(jax.tree.leaves(nnx.state(hierarchy, nnx.Param)), jax.tree.leaves(nnx.state(loaded, nnx.Param))):
    np.testing.assert_array_equal(a, b)
  with pytest.raises(FileNotFoundError, match="no trained model"):
    checkpoint.load_policy(str(tmp_path / "empty"))


def _damaged(path, original: bytes):
  """A file's bytes flipped here and there, cut in half, and emptied."""
  flipped = bytearray(original)
  for i in range(0, len(flipped), max(1, len(flipped) // 50)):
    flipped[i] ^= 0xFF
  return [bytes(flipped), original[:len(original) // 2], b""]


def _each_damaged_file(directory):
  """Yields each file under directory damaged each way (`_damaged`), restoring it afterwards."""
  for path in sorted(p for p in directory.rglob("*") if p.is_file()):
    original = path.read_bytes()
    for content in _damaged(path, original):
      path.write_bytes(content)
      yield path
    path.write_bytes(original)


def test_corrupt_or_mismatched_saved_files_are_refused_naming_the_file(tmp_path):
  config = TrainConfig(hidden=(8,), seed=1)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, config)
  workdir = tmp_path / "model"
  checkpoint.save_hierarchy(str(workdir), "nanocraft", hierarchy, config.hidden)
  for damaged in _each_damaged_file(workdir / checkpoint.MODEL_DIR):  # every file of the parameters
    with pytest.raises(checkpoint.CheckpointError, match=f"{damaged.name} does not match its checksum in .*model.json"):
      checkpoint.load_policy(str(workdir))
  description = (workdir / "model.json").read_text()
  architecture = json.loads(description)
  for content, message in [
      (json.dumps({**architecture, "hidden": [16]}), "edited or corrupt"),
      (json.dumps({**architecture, "capacity": [1]}), "edited or corrupt"),
      (json.dumps({**architecture, "spec": {**architecture["spec"], "action_sizes": [2 ** 40]}}), "edited or corrupt"),
      (description[:20], "corrupt or truncated JSON"), ("[]", "not a model description")]:
    (workdir / "model.json").write_text(content)
    with pytest.raises(checkpoint.CheckpointError, match=message):
      checkpoint.load_policy(str(workdir))
  (workdir / "model.json").write_text(description)
  wider = networks.make_hierarchy(NANOCRAFT.spec, dataclasses.replace(config, hidden=(16,)))
  checkpoint.save_hierarchy(str(tmp_path / "wide"), "nanocraft", wider, (16,))
  shutil.rmtree(workdir / checkpoint.MODEL_DIR)
  shutil.copytree(tmp_path / "wide" / checkpoint.MODEL_DIR, workdir / checkpoint.MODEL_DIR)
  with pytest.raises(checkpoint.CheckpointError, match=r"(listed|checksum) in .*model.json"):  # another run's
    checkpoint.load_policy(str(workdir))
  wide_files = json.loads((tmp_path / "wide" / "model.json").read_text())["files"]
  unsigned = {k: v for k, v in architecture.items() if k != "sha256"}
  (workdir / "model.json").write_text(json.dumps(storage.signed({**unsigned, "files": wide_files})))
  with pytest.raises(checkpoint.CheckpointError, match=r"is float32\[.*16.*the model needs"):  # signed anew
    checkpoint.load_policy(str(workdir))
  path = tmp_path / "checkpoint"
  resume.write_training(str(path), hierarchy, {"level": 2, "report": {}}, None, {})
  assert resume.read_training(str(path))[0]["level"] == 2
  for damaged in _each_damaged_file(path):  # state.json and every file of the arrays
    with pytest.raises(checkpoint.CheckpointError, match="state.json: corrupt|state.json: edited|does not match"):
      resume.read_training(str(path))
  (path / "state.json").write_text("[]")
  with pytest.raises(checkpoint.CheckpointError, match="state.json: not a training checkpoint"):
    resume.read_training(str(path))


def test_resume_check_names_what_differs_and_takes_defaults_for_settings_a_checkpoint_predates():
  config = TrainConfig(hidden=(8,), seed=1, training="levelwise", batch_size=0)  # resolved, as checkpoints record it
  settings = {"config": json.loads(json.dumps(dataclasses.asdict(config))), "levels": [1, 2], "demonstrations": "x"}
  older = {**settings, "config": {k: v for k, v in settings["config"].items() if k != "training"}}
  resume.check_resumable("ckpt", older, settings)  # made before --training existed: level-wise, its default
  unresolved = {**settings, "config": {**settings["config"], "batch_size": None}}
  resume.check_resumable("ckpt", unresolved, settings)  # recorded before runs resolved it: None was the full batch
  no_snapshot = {**settings, "config": {k: v for k, v in settings["config"].items() if k != "snapshot"}}
  with pytest.raises(checkpoint.CheckpointError, match="snapshot: 'earliest' there, 'latest' here"):
    resume.check_resumable("ckpt", no_snapshot, settings)  # runs before --snapshot kept the earliest
  joint = json.loads(json.dumps(dataclasses.asdict(dataclasses.replace(config, training="joint"))))
  with pytest.raises(checkpoint.CheckpointError, match="training: 'levelwise' there, 'joint' here"):
    resume.check_resumable("ckpt", older, {**settings, "config": joint})
  with pytest.raises(checkpoint.CheckpointError, match="seed: 1 there, 2 here"):
    resume.check_resumable("ckpt", settings, {**settings, "config": {**settings["config"], "seed": 2}})
  with pytest.raises(checkpoint.CheckpointError, match="demonstrations differ"):
    resume.check_resumable("ckpt", settings, {**settings, "demonstrations": "y"})
  with pytest.raises(checkpoint.CheckpointError, match="observes differ \\(another hierarchy: what its procedures"):
    resume.check_resumable("ckpt", settings, {**settings, "observes": [None, [[0], [1]]]})


def test_the_demonstrations_digest_reads_observations_values_not_their_type():
  from php_jax.demos import compacted
  task = tasks.get("nanocraft")
  demos = datasets.training_demos(task, 1, 4, 2)
  config = TrainConfig()
  digest = resume.run_settings(task.spec, demos, config)["demonstrations"]
  assert compacted(demos).observations.dtype == np.uint8
  assert resume.run_settings(task.spec, compacted(demos), config)["demonstrations"] == digest
  observations = np.array(demos.observations)
  observations[0, 0, 0] += 1
  assert resume.run_settings(task.spec, demos._replace(observations=observations), config)["demonstrations"] != digest


@pytest.mark.slow
def test_nanocraft_run_solves_held_out_episodes_and_evaluate_loads_it(tmp_path):
  """A small strongly supervised run through the CLI learns a hierarchy that solves fresh episodes."""
  import json
  import subprocess
  import sys
  workdir = tmp_path / "nc"
  proc = subprocess.run([sys.executable, "-m", "experiments.nanocraft", f"--workdir={workdir}", "--num_demos=16",
                         "--num_strong=16", "--training=levelwise", "--iterations=1000", "--hidden=32", "--root=mlp",
                         "--learning_rate=1e-2", "--eval_every=200", "--num_test=200", "--seed=0"], capture_output=True, text=True, timeout=900)
  assert proc.returncode == 0, proc.stderr[-3000:]
  results = json.loads((workdir / "results.json").read_text())
  assert results["test"]["accuracy"] >= 0.8, results["test"]
  assert set(results["levels"]) == {"0", "1", "2"} and results["levels"]["0"]["best_iteration"] is not None
  assert results["commit"] is None or len(results["commit"].removesuffix("+dirty")) == 40  # provenance
  assert results["versions"]["jax"] == jax.__version__ and results["versions"]["platform"] == jax.devices()[0].platform
  assert (workdir / "metrics.jsonl").read_text().count("\n") > 10
  proc = subprocess.run([sys.executable, "-m", "experiments.segment_errors", f"--run={workdir}"], capture_output=True,
                        text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-3000:]
  assert [json.loads(line)["level"] for line in proc.stdout.splitlines()] == [2, 1]  # no weak demonstration
  problems = tmp_path / "p.jsonl"
  problems.write_text("".join(json.dumps({"x": x, "y": y, "w": w, "h": h, "preplaced": pre}) + "\n"
                              for x, y, w, h, pre in nanocraft_task.random_problems(7, 20)))
  out = tmp_path / "out.jsonl"
  proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--task=nanocraft", f"--policy={workdir}",
                         f"--problems={problems}", f"--out={out}"], capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr[-3000:]
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert len(rows) == 20 and sum(r["correct"] for r in rows) >= 14
  sums = tmp_path / "sums.jsonl"
  sums.write_text('{"a": "12", "b": "34"}\n')
  wrong_task = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--task=addition",
                               f"--policy={workdir}", f"--problems={sums}", f"--out={out}"],
                              capture_output=True, text=True, timeout=300)
  assert wrong_task.returncode == 2 and "holds a nanocraft model" in wrong_task.stderr


@pytest.mark.slow
def test_small_addition_run_solves_longer_problems_and_decodes_the_supervisors_segmentation():
  """Trained on 5-digit sums (strong: a set covering all 200 columns; weak: 10 random sums of 1–5 digits),
  the hierarchy adds 20-digit numbers, and decoding the weak demonstrations recovers the supervisor's stacks."""
  strong = addition_task.covering_problems(0, 5)
  problems = strong + addition_task.random_problems(1, range(1, 6), 2)
  demos = _addition_demos(problems, num_strong=len(strong))
  config = TrainConfig(iterations=600, eval_every=100, hidden=(32,), root="mlp", root_hidden=32,
                             learning_rate=1e-2, tau_in_termination=(False, True, True), decode="viterbi")
  validation = addition_task.random_problems(2, range(1, 6), 4)
  hierarchy, report = levelwise.train_hierarchy(ADDITION.spec, demos, config,
                                            lambda h: evaluation.accuracy(ADDITION, h, validation),
                                            log=lambda row: None)
  assert report[2]["decoding_agreement"] >= 0.95 and report[1]["decoding_agreement"] >= 0.95, report
  assert evaluation.accuracy(ADDITION, hierarchy, addition_task.random_problems(3, [20], 20)) == 1.0


class _Interrupt(Exception):
  pass


@pytest.mark.slow
@pytest.mark.parametrize("warmup, stops", [(0, [(1, 40), (0, 60)]), (20, [(2, 20), (1, 60), (0, 60)])])
def test_interrupted_training_resumes_to_the_same_result(tmp_path, warmup, stops):
  problems = nanocraft_task.random_problems(3, 8)
  demos = datasets.oracle_demonstrations(NANOCRAFT, nanocraft_task.make_states(problems), 4,
                                         nanocraft.ORACLE_STEP_BUDGET)
  config = TrainConfig(iterations=60, eval_every=20, hidden=(8,), root="mlp", root_hidden=8,
                             learning_rate=1e-2, decode="sample", strong_warmup=warmup, seed=5)
  validation = nanocraft_task.random_problems(4, 8)

  def validate(h):
    return float(np.mean([o["correct"] for o in evaluation.solve(NANOCRAFT, h, validation)]))

  def run(path, stop_at=None):
    def log(row):
      if stop_at and (row.get("level"), row.get("iteration")) == stop_at:
        raise _Interrupt
    return levelwise.train_hierarchy(NANOCRAFT.spec, demos, config, validate, log=log, checkpoint_path=path)

  reference, ref_report = run(str(tmp_path / "uninterrupted"))
  path = str(tmp_path / "interrupted")
  for stop_at in stops:  # mid-level (at the end of the warmup), then at the root level's last iteration
    with pytest.raises(_Interrupt):
      run(path, stop_at)
  resumed, report = run(path)
  for a, b in zip(jax.tree.leaves(nnx.state(reference, nnx.Param)), jax.tree.leaves(nnx.state(resumed, nnx.Param))):
    np.testing.assert_array_equal(a, b)
  for level in range(3):
    assert report[level]["losses"] == ref_report[level]["losses"]
    assert report[level]["best_iteration"] == ref_report[level]["best_iteration"]
    assert report[level].get("decoding_agreement") == ref_report[level].get("decoding_agreement")


@pytest.mark.slow
def test_strong_warmup_fits_the_strong_views_alone_first():
  problems = nanocraft_task.random_problems(3, 6)
  demos = datasets.oracle_demonstrations(NANOCRAFT, nanocraft_task.make_states(problems), 2,
                                         nanocraft.ORACLE_STEP_BUDGET)
  view = views.lowest_view(demos, NANOCRAFT.spec.num_levels)
  config = TrainConfig(iterations=0, hidden=(8,), root="mlp", root_hidden=8, strong_weight=2.0, seed=1)

  def trained(part, **changes):
    model = objective.LevelModel(networks.make_hierarchy(NANOCRAFT.spec, config).levels[2],
                             networks.make_root(NANOCRAFT.spec, 2, config))
    levelwise.train_level(model, part, 2, dataclasses.replace(config, **changes), fitting.Hooks(log=lambda row: None))
    return jax.tree.leaves(nnx.state(model, nnx.Param))

  strong_only = trained(views.select(view, view.strong), iterations=30)
  for a, b in zip(trained(view, strong_warmup=30), strong_only):
    np.testing.assert_array_equal(a, b)  # the weak views played no part in the first 30 iterations
  assert any(not np.array_equal(a, b) for a, b in zip(trained(view, strong_warmup=30, iterations=5), strong_only))


@pytest.mark.slow
def test_root_strong_weight_changes_only_the_root_levels_loss():
  demos = datasets.training_demos(tasks.get("nanocraft"), seed=3, num_demos=6, num_strong=2)
  config = TrainConfig(iterations=1, hidden=(8,), root="mlp", root_hidden=8, strong_weight=5.0, seed=2)

  def first_losses(**changes):
    _, report = levelwise.train_hierarchy(NANOCRAFT.spec, demos, dataclasses.replace(config, **changes),
                                      log=lambda row: None)
    return [report[level]["losses"][0][1] for level in (2, 1, 0)]

  default, root_weight_1 = first_losses(), first_losses(root_strong_weight=1.0)
  assert default[:2] == root_weight_1[:2] and default[2] > root_weight_1[2]  # weak views now count as much


def test_call_penalty_is_a_prior_on_the_number_of_calls():
  demos = datasets.training_demos(tasks.get("nanocraft"), seed=3, num_demos=6, num_strong=3)
  config = TrainConfig(hidden=(8,), root="mlp", root_hidden=8, seed=2)
  view = views.device_view(views.lowest_view(demos, NANOCRAFT.spec.num_levels))
  php, root = networks.make_hierarchy(NANOCRAFT.spec, config).levels[2], networks.make_root(NANOCRAFT.spec, 2, config)
  capacity, penalty = levelwise.level_capacity(view, 2, config), 1.5
  for b in range(view.length.shape[0]):
    one = jax.tree.map(lambda x: x[b], view)
    n = one.length
    free = objective.lattice_inputs(objective.LevelModel(php, root), one, capacity)
    penalised = objective.lattice_inputs(objective.LevelModel(php, root, penalty), one, capacity)

    def log_likelihood(cost):
      return lattice.forward_backward(free._replace(log_root=free.log_root - cost)).log_likelihood

    if view.strong[b]:  # one known path: its log-likelihood drops by the penalty once per call
      calls = np.sum(np.asarray(one.counters[:n]) == 0)
      np.testing.assert_allclose(log_likelihood(penalty), log_likelihood(0.0) - penalty * calls, rtol=1e-5)
    else:  # d/dλ log Σ_ζ P(ζ, ξ) e^(−λ·calls(ζ)) = −E[calls | ξ] under the penalised posterior
      posterior = lattice.forward_backward(penalised)
      expected_calls = jnp.sum(posterior.v[:, :, 0])
      np.testing.assert_allclose(jax.grad(log_likelihood)(penalty), -expected_calls, rtol=1e-4)
      unpenalised_calls = jnp.sum(lattice.forward_backward(free).v[:, :, 0])
      assert expected_calls <= unpenalised_calls + 1e-4
  with pytest.raises(ValueError, match="call_penalty"):
    levelwise.train_hierarchy(NANOCRAFT.spec, demos, dataclasses.replace(config, call_penalty=(0.0, 1.0)))
  with pytest.raises(ValueError, match="call_penalty"):
    levelwise.train_hierarchy(NANOCRAFT.spec, demos, dataclasses.replace(config, call_penalty=(1.0, 1.0, 0.0)))


@pytest.mark.parametrize("rule, kept", [("earliest", 20), ("latest", 30)])
def test_fit_keeps_the_earliest_or_latest_of_the_best_validated_snapshots(rule, kept):
  model = nnx.Linear(2, 1, rngs=nnx.Rngs(0))
  scores = iter([0.5, 1.0, 1.0, 0.9])
  snapshots = {}

  def on_eval(iteration, loss):
    snapshots[iteration] = np.asarray(model.kernel[...]).copy()
    return next(scores)

  progress = fitting.fit(model, lambda m: jnp.sum(m(jnp.ones((1, 2))) ** 2), fitting.Schedule(40, 0.1, 10, rule),
                         fitting.Hooks(on_eval, lambda row: None))
  assert progress.best_iteration == kept and progress.best_score == 1.0
  np.testing.assert_array_equal(model.kernel[...], snapshots[kept])
  with pytest.raises(ValueError, match="snapshot must be one of"):
    fitting.fit(model, lambda m: jnp.sum(m(jnp.ones((1, 2)))), fitting.Schedule(1, 0.1, 1, "best"))


def test_fit_saves_by_time_between_evaluations_and_resumes_from_there():
  def run(resume=None, saves=None):
    model = nnx.Linear(2, 1, rngs=nnx.Rngs(0))
    progress = fitting.fit(model, lambda m: jnp.sum((m(jnp.ones((1, 2))) - 3.0) ** 2),
                           fitting.Schedule(40, 0.1, 10, save_seconds=0.0),
                           fitting.Hooks(log=lambda row: None, save=saves.append if saves is not None else None),
                           resume=resume)
    return progress, model

  saves = []
  reference, model = run(saves=saves)
  assert [s.iteration for s in saves] == list(range(1, 41))  # every iteration, evaluations included
  resumed, resumed_model = run(resume=saves[14])  # iteration 15, between evaluations
  np.testing.assert_array_equal(resumed_model.kernel[...], model.kernel[...])
  assert resumed.losses == reference.losses


def test_fit_can_pass_the_update_count_to_the_loss():
  """An IterationLoss is given the number of updates made before it (0 at the first), resumed too."""
  model = nnx.Linear(1, 1, rngs=nnx.Rngs(0))

  def loss(m, iteration, x):
    return jnp.sum(m(x) * 0.0) + iteration

  schedule, hooks = fitting.Schedule(6, 0.1, 1), fitting.Hooks(log=lambda row: None)
  saved = []
  progress = fitting.fit(model, fitting.IterationLoss(loss), schedule._replace(iterations=3),
                         fitting.Hooks(log=lambda row: None, save=saved.append), args=(jnp.ones((2, 1)),))
  assert [value for _, value in progress.losses] == [0, 1, 2]
  resumed = fitting.fit(model, fitting.IterationLoss(loss), schedule, hooks, resume=saved[-1],
                        args=(jnp.ones((2, 1)),))
  assert [value for _, value in resumed.losses] == [0, 1, 2, 3, 4, 5]


def test_fit_with_weight_decay_shrinks_what_the_loss_does_not_hold():
  """Schedule.weight_decay: AdamW's decoupled decay; with a loss that ignores the parameters, each update
  multiplies them by 1 − learning_rate · weight_decay (the update count still reaches the loss)."""
  model = nnx.Linear(2, 1, rngs=nnx.Rngs(0))
  start = np.asarray(model.kernel[...]).copy()
  progress = fitting.fit(model, fitting.IterationLoss(lambda m, iteration: jnp.sum(m(jnp.ones((1, 2))) * 0.0)
                                                     + iteration),
                         fitting.Schedule(5, 0.1, 1, weight_decay=0.5), fitting.Hooks(log=lambda row: None))
  assert [value for _, value in progress.losses] == [0, 1, 2, 3, 4]
  np.testing.assert_allclose(model.kernel[...], start * 0.95 ** 5, rtol=1e-5)
