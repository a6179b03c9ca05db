"""A training run in a workdir, from start to results: the workdir's files, the metrics log, resuming, the
saved model and results.json, whichever model and training mode the settings ask for.

A run writes workdir/metrics.jsonl (one JSON row per logged event, each with "seconds" since the run
started), workdir/checkpoint/ while it trains (a rerun resumes from it, ending as an uninterrupted
run would: rows logged after the checkpoint are dropped and logged again), the model (model.json and
model/, which `checkpoint.load_policy` reads) and results.json (settings, training summary, test
results, wall time, the code's commit and the package versions). Several seeds trained as one program
(`train_and_evaluate_seeds`) write one such run per seed, in workdir/seed=S, and their common progress in
workdir/seeds_checkpoint/. Of several processes (jax.distributed), only the first writes files.
"""
from __future__ import annotations

import contextlib
import dataclasses
import fcntl
import glob
import json
import os
import time
from typing import Any, Callable

import jax
from flax import nnx
from jax.experimental import multihost_utils

from php_jax import fitting, flat
from php_jax.data import files
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.training import call_graph, checkpoint, joint, levelwise, provenance, resume, storage
from php_jax.training.config import TrainConfig, in_mode, resolved, with_common_buckets

METRICS_FILE, RESULTS_FILE, SEEDS_CHECKPOINT = "metrics.jsonl", "results.json", "seeds_checkpoint"
REPORT_FILE = "report.html"  # the training commands write it (`experiments.common.run_report`); --overwrite clears it
RUN_FILES = (checkpoint.TRAINING_DIR, METRICS_FILE, RESULTS_FILE, checkpoint.ARCHITECTURE_FILE,
             checkpoint.MODEL_DIR, REPORT_FILE)


class WorkdirError(ValueError):
  """A workdir that cannot hold a run; the message names it."""


@dataclasses.dataclass(frozen=True)
class Experiment:
  """What one run trains on and how it is judged.

  Attributes:
    name: the task's name (model.json records it, for `experiments.evaluate`).
    spec: the hierarchy's levels, action factor sizes and observation size.
    demos: the training demonstrations [B, ...].
    validate: model → validation score (the kept snapshot has the best).
    test: model → the test results (results.json's "test").
    extra: more entries for results.json (e.g. the seed and the data set's sizes).
    action_name: an elementary action (a list of ints, one per factor) → its text, for messages.
    numbers: per demonstration, its number in messages (e.g. its place among a file's demonstrations, from 0);
      None: its index in demos.
    validation_demos: held-out demonstrations, on which the split search judges its candidates
      (`TrainConfig.split_rounds`); None: the training demonstrations.
  """
  name: str
  spec: HierarchySpec
  demos: Demonstration
  validate: Callable[[Any], float]
  test: Callable[[Any], dict]
  extra: dict
  action_name: Callable[[list[int]], str] = str
  numbers: tuple[int, ...] | None = None
  validation_demos: Demonstration | None = None


def print_row(row: dict) -> None:
  """A logged row (or the final test results) as one JSON line on stdout: what a run shows by default."""
  print(json.dumps(row), flush=True)


def train_and_evaluate(experiment: Experiment, config: TrainConfig, workdir: str, overwrite: bool = False,
                       flat_model: flat.FlatModel | None = None, wait: bool = False,
                       echo: Callable[[dict], None] = print_row) -> dict:
  """Trains a PHP hierarchy by config.training (resuming the workdir's checkpoint if an earlier run was
  interrupted), or with flat_model that flat baseline (`flat.FlatModel`); saves it, tests it,
  writes results.json; returns the results. overwrite: delete an earlier run's files first (else it is
  resumed, or refused with CheckpointError if its settings differ; a finished run with the same settings is
  not trained again: its results are shown and returned). The run holds the workdir's lock
  throughout (`workdir_lock`; wait: for another run holding it to end). echo(row) shows each logged row and
  last the test results."""
  # resolved here, so that results.json records it
  config = resolved(config, experiment.demos, experiment.spec, flat_model is not None)
  commit = provenance.code_version()  # the code as it was when the run started
  spec = experiment.spec
  with workdir_lock(workdir, wait):
    clear_workdir(workdir, RUN_FILES, overwrite)
    finished = _finished(workdir, experiment, config, flat_model)
    if finished:
      echo({"test": finished["test"], "wall_seconds": finished["wall_seconds"], "finished_before": True})
      return finished
    gaps = {} if flat_model else annotation_gaps(experiment, config, echo)
    with MetricsLog(workdir, echo=echo) as log:
      if flat_model:
        model, trained = _train_flat(experiment, config, flat_model, log)
        checkpoint.save_flat(workdir, experiment.name, model, spec)
      else:
        model, trained, capacity = _train_php(experiment, config, log,
                                              os.path.join(workdir, checkpoint.TRAINING_DIR))
        checkpoint.save_hierarchy(workdir, experiment.name, model, config.hidden, capacity)
    results = {"task": experiment.name, "model": flat_model.name if flat_model else "php",
               "config": dataclasses.asdict(config), **experiment.extra, **gaps, **trained}
    log.echo({"phase": "testing"})
    return _write_results(workdir, results, experiment.test(model), log, commit)


def train_and_evaluate_seeds(experiments: list[Experiment], configs: list[TrainConfig], workdir: str,
                             overwrite: bool = False, wait: bool = False,
                             echo: Callable[[dict], None] = print_row) -> list[dict]:
  """train_and_evaluate for several seeds' PHP hierarchies (experiments[s] with configs[s]), trained
  level-wise as one program (`levelwise.train_seeds`): seed s's run goes to workdir/seed=S with the files its
  separate run would write, its results.json also naming the seeds trained with it ("trained_with_seeds":
  its wall time and per-level seconds are those of the shared program); the progress of all is checkpointed
  in workdir/seeds_checkpoint/ and resumed from there. The run holds the locks of workdir and of every
  seed's workdir throughout."""
  workdirs = [os.path.join(workdir, f"seed={c.seed}") for c in configs]
  configs = with_common_buckets([resolved(in_mode(c, "levelwise"), e.demos, e.spec)
                                 for c, e in zip(configs, experiments)])
  commit, spec = provenance.code_version(), experiments[0].spec
  with contextlib.ExitStack() as stack:
    for locked in (workdir, *workdirs):  # each seed's workdir too, as its separate run would
      stack.enter_context(workdir_lock(locked, wait))
    clear_workdir(workdir, (SEEDS_CHECKPOINT,), overwrite)
    for run_dir in workdirs:
      clear_workdir(run_dir, RUN_FILES, overwrite)
    finished = [_finished(run_dir, e, c, None) for run_dir, e, c in zip(workdirs, experiments, configs)]
    if all(finished):
      for c, results in zip(configs, finished):
        echo({"seed": c.seed, "test": results["test"], "wall_seconds": results["wall_seconds"],
              "finished_before": True})
      return finished
    gaps = [annotation_gaps(e, c, lambda row, seed=c.seed: echo({"seed": seed, **row}))
            for e, c in zip(experiments, configs)]
    logs = [stack.enter_context(MetricsLog(run_dir, {"seed": c.seed}, echo)) for run_dir, c in zip(workdirs, configs)]
    trained = levelwise.train_seeds(spec, [e.demos for e in experiments], configs, [e.validate for e in experiments],
                                log=lambda s, row: logs[s](row),
                                checkpoint_path=os.path.join(workdir, SEEDS_CHECKPOINT),
                                seed_checkpoint_paths=[os.path.join(w, checkpoint.TRAINING_DIR) for w in workdirs])
    for run_dir, e, (hierarchy, report) in zip(workdirs, experiments, trained):
      checkpoint.save_hierarchy(run_dir, e.name, hierarchy, configs[0].hidden,
                                [report[level]["capacity"] for level in range(spec.num_levels)])
    for log in logs:
      log.close()
    together = {"trained_with_seeds": [c.seed for c in configs]}  # its times are the shared program's
    echo({"phase": "testing"})
    return [_write_results(run_dir, {"task": e.name, "model": "php", "config": dataclasses.asdict(c), **e.extra,
                                     **gap, **together, **_levels(report)}, e.test(hierarchy), log, commit)
            for run_dir, c, e, (hierarchy, report), log, gap in zip(workdirs, configs, experiments, trained, logs,
                                                                      gaps)]


def annotation_gaps(experiment: Experiment, config: TrainConfig, echo: Callable[[dict], None]) -> dict:
  """Warns, through echo({"warning": text}), of each pair of consecutive actions that the call graph may have
  locked out (`call_graph.unshown_pairs`); returns results.json's entry for them, {"annotation_gaps": [...]},
  or {} where there are none."""
  spec, demos, name = experiment.spec, experiment.demos, experiment.action_name
  pairs = call_graph.unshown_pairs(demos, spec, call_graph.resolve(config.call_graph, demos, spec))
  weak = int(len(demos.strong) - demos.strong.sum())
  number = (lambda b: b) if experiment.numbers is None else experiment.numbers.__getitem__
  pairs = [dataclasses.replace(p, example=number(p.example)) for p in pairs]
  for pair in pairs:
    first, second = name(list(pair.first)), name(list(pair.second))
    echo({"warning": f"{pair.demonstrations} of the {weak} actions-only demonstrations take '{first}' then "
                     f"'{second}' (the first: demonstration {pair.example}), the annotated ones never do, and "
                     f"with --call_graph={config.call_graph} no procedure that takes '{first}' may take "
                     f"'{second}': each of those steps is split between two calls. If one procedure should take "
                     "both, annotate a demonstration that shows it (experiments.suggest chooses)"})
  return {"annotation_gaps": [{"first": list(p.first), "second": list(p.second), "demonstrations":
                               p.demonstrations, "example": p.example} for p in pairs]} if pairs else {}


def _finished(workdir: str, experiment: Experiment, config: TrainConfig,
              flat_model: flat.FlatModel | None) -> dict | None:
  """The results.json of a run that finished in workdir with these settings; None if no run finished there
  (`read_finished`). Raises WorkdirError (or CheckpointError, for other demonstrations) naming the settings
  that differ if it was made with others."""
  results = read_finished(workdir)
  if results is None:
    return None
  model = flat_model.name if flat_model else "php"
  differ = other_settings(results, {"task": experiment.name, "model": model, **experiment.extra}, config)
  if flat_model and (results.get(model) or {}).get("hidden") != flat_model.hidden:
    differ.append(f"--flat_hidden: {(results.get(model) or {}).get('hidden')!r} there, {flat_model.hidden} here")
  if differ:
    raise made_otherwise(workdir, differ)
  saved = resume.read_training(os.path.join(workdir, checkpoint.TRAINING_DIR))
  if saved is not None and model == "php":  # the demonstrations' digest: another data file, say
    resume.check_resumable(os.path.join(workdir, checkpoint.TRAINING_DIR), saved[0].get("settings", {}),
                          resume.run_settings(experiment.spec, experiment.demos, config))
  return results


def read_finished(workdir: str) -> dict | None:
  """workdir's results.json where a run finished there (with its model), a JSON object holding its "config"
  and "test" results; None where none did, or where results.json cannot be read (the run then resumes and
  writes it again)."""
  paths = [os.path.join(workdir, name) for name in (RESULTS_FILE, checkpoint.ARCHITECTURE_FILE, checkpoint.MODEL_DIR)]
  if not all(map(os.path.exists, paths)):
    return None
  try:
    with open(paths[0], encoding="utf-8") as f:
      results = json.load(f)
  except (OSError, ValueError):
    return None
  if not isinstance(results, dict) or not isinstance(results.get("config"), dict) or "test" not in results:
    return None
  return results


def other_settings(results: dict, expected: dict, config: TrainConfig | None) -> list[str]:
  """What a finished run's results.json records otherwise than this run asks, each "name: there, here": its
  entries named in expected, and (config given) its settings; a strong weight differs with the data, so it is
  named only where nothing else differs."""
  expected = json.loads(json.dumps(expected))
  differ = [f"{k}: {results.get(k)!r} there, {v!r} here" for k, v in expected.items() if results.get(k) != v]
  if config is not None:
    saved_config = resume.saved_config(results["config"])
    config_json = json.loads(json.dumps(dataclasses.asdict(config)))
    differ += [f"--{k}: {saved_config.get(k)!r} there, {v!r} here" for k, v in config_json.items()
               if saved_config.get(k) != v and not (k == "strong_weight" and differ)]
  return differ


def made_otherwise(workdir: str, differ: list[str]) -> WorkdirError:
  """The refusal of a workdir whose finished run was made with other settings (`other_settings`)."""
  return WorkdirError(f"{workdir} holds a finished run made with other settings ({'; '.join(differ)}); use a "
                      "fresh workdir, or --overwrite to train again")


LOCK_FILE = ".lock"


@contextlib.contextmanager
def workdir_lock(workdir: str, wait: bool = False):
  """Makes workdir (WorkdirError if a file has that name) and holds its lock while the block runs: an
  exclusive `fcntl.flock` on workdir/.lock, which the kernel releases when the process ends, however it
  ends, so a lock left by a killed run never blocks. If another run holds it: WorkdirError naming that run's
  pid, or with wait, waiting for it to end. The lock file is removed as the block ends (a killed run's
  stays, holding its pid). Of several processes (jax.distributed), process 0 takes it."""
  if os.path.exists(workdir) and not os.path.isdir(workdir):
    raise WorkdirError(f"{workdir} is a file, not a directory")
  if jax.process_index() != 0:
    yield
    return
  os.makedirs(workdir, exist_ok=True)
  path = os.path.join(workdir, LOCK_FILE)
  while True:
    lock = open(path, "a+")
    try:
      fcntl.flock(lock, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
    except BlockingIOError:
      lock.seek(0)
      holder = lock.read().strip() or "unknown"
      lock.close()
      raise WorkdirError(f"{workdir} is in use by another run (pid {holder}); wait for it to end, or give "
                         "--wait to wait for it") from None
    if _is_file_at(lock, path):
      break
    lock.close()  # the run that held it removed it as it ended: lock the file now at path
  try:
    lock.truncate(0)
    lock.write(str(os.getpid()))
    lock.flush()
    yield
  finally:
    if _is_file_at(lock, path):  # while still held: a run waiting on this file finds it gone and locks a new one
      with contextlib.suppress(FileNotFoundError):
        os.unlink(path)
    fcntl.flock(lock, fcntl.LOCK_UN)
    lock.close()


def _is_file_at(opened, path: str) -> bool:
  try:
    return os.stat(path).st_ino == os.fstat(opened.fileno()).st_ino
  except FileNotFoundError:
    return False


def clear_workdir(workdir: str, files: tuple[str, ...], overwrite: bool = False) -> None:
  """In a workdir `workdir_lock` holds: with overwrite, deletes `files` there first (and files of an older
  php_jax, which without overwrite raise WorkdirError); removes what a write cut off by SIGKILL left."""
  if jax.process_index() == 0:  # of several processes (jax.distributed), the one that writes files
    older = [name for name in checkpoint.OLDER_FILES if os.path.exists(os.path.join(workdir, name))]
    if older and not overwrite:
      raise WorkdirError(f"{os.path.join(workdir, older[0])} was saved by an older php_jax; use a fresh workdir, "
                         "or --overwrite to train again")
    for name in (*files, *older) if overwrite else ():
      storage.remove_saved(os.path.join(workdir, name))
    for pattern in (".*.tmp", storage.TEMPORARY, os.path.join("*", storage.TEMPORARY)):  # checkpoint/'s too
      for leftover in glob.glob(os.path.join(glob.escape(workdir), pattern)):
        storage.remove_saved(leftover)
  if jax.process_count() > 1:  # the others read the workdir (to resume) once process 0 has cleared it
    multihost_utils.sync_global_devices("workdir ready")


class MetricsLog:
  """A run's metrics.jsonl (process 0's) and clock: each row logged gets "seconds" since the run started, is
  appended and shown by echo (with `label` added to the shown copy). A {"resumed": True, "logged": n} row keeps
  the file's first n rows, and the clock goes on from the last of them; a run whose first row is another
  (it resumes nothing) starts the file afresh, so that rows of an attempt killed before its first checkpoint
  are not kept twice."""

  def __init__(self, workdir: str, label: dict | None = None, echo: Callable[[dict], None] = print_row):
    self.path, self.label, self.start = os.path.join(workdir, METRICS_FILE), label or {}, time.time()
    self.file, self.first, self.echo = None, True, echo

  def __enter__(self):
    if jax.process_index() == 0:
      self.file = open(self.path, "a")
    return self

  def __exit__(self, *exc):
    self.close()

  def close(self) -> None:
    if self.file:
      self.file.close()
      self.file = None

  def __call__(self, row: dict) -> None:
    if row.get("resumed"):
      self.start -= _keep_rows(self.file, self.path, row["logged"])
    else:
      if self.first and self.file:
        self.file.truncate(0)
      row = {**row, "seconds": round(time.time() - self.start, 2)}
      if self.file:
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
    self.first = False
    self.echo({**self.label, **row})


def _keep_rows(metrics, path: str, count: int) -> float:
  """Truncates the open metrics file (None: only reads it) to its first `count` rows; returns the last kept
  row's "seconds"."""
  with open(path, "rb") as f:
    rows = f.read().splitlines(keepends=True)[:count]
  if metrics:
    metrics.truncate(sum(map(len, rows)))
  return json.loads(rows[-1])["seconds"] if rows else 0.0


def _write_results(workdir: str, results: dict, test_results: dict, log: MetricsLog, commit) -> dict:
  """results.json: `results` with the test results, wall time (on log's clock), commit and versions; returns
  it. Shows the test results and wall time through log's echo (with its label)."""
  results = {**results, "test": test_results, "wall_seconds": round(time.time() - log.start, 1), "commit": commit,
             "versions": provenance.environment_versions()}
  files.write_atomically(os.path.join(workdir, RESULTS_FILE), json.dumps(results, indent=1).encode())
  log.echo({**log.label, "test": test_results, "wall_seconds": results["wall_seconds"]})
  return results


def _train_php(experiment: Experiment, config: TrainConfig, log, path: str):
  """(hierarchy, its results.json entries, capacity per level) by config.training: {"levels": {level: summary}}
  level-wise, {"joint": summary} joint."""
  spec, demos, validate = experiment.spec, experiment.demos, experiment.validate
  if config.training == "joint":
    hierarchy, report = joint.train_joint(spec, demos, config, validate, log=log, checkpoint_path=path,
                                          validation_demos=experiment.validation_demos)
    return hierarchy, {"joint": _summary(report)}, report["capacity"]
  hierarchy, report = levelwise.train_hierarchy(spec, demos, config, validate, log=log, checkpoint_path=path)
  return hierarchy, _levels(report), [report[level]["capacity"] for level in range(spec.num_levels)]


def _levels(report: dict) -> dict:
  """results.json's entry of a level-wise report."""
  return {"levels": {str(level): _summary(entry) for level, entry in report.items()}}


def _summary(entry: dict) -> dict:
  """A training report entry without its loss curve (metrics.jsonl has it), with the final loss."""
  return {k: v for k, v in entry.items() if k != "losses"} | {
      "final_loss": entry["losses"][-1][1] if entry["losses"] else None}


def _train_flat(experiment: Experiment, config: TrainConfig, model: flat.FlatModel, log):
  """The baseline on the same demonstrations' elementary actions (annotations unused), same iterations,
  learning rate, seed and snapshot rule."""
  spec = experiment.spec
  policy = flat.FlatPolicy(spec.obs_dim, spec.action_sizes, model.hidden, spec.observation, cell=model.cell,
                           rngs=nnx.Rngs(config.network_seed))
  schedule = config.schedule()
  report = flat.train(policy, experiment.demos, schedule,
                      fitting.Hooks(lambda iteration, loss: experiment.validate(policy), log))
  return policy, {model.name: {"hidden": model.hidden, "best_iteration": report["best_iteration"],
                               "validation": report["validation"], "final_loss": report["losses"][-1][1]}}
