"""Shared plumbing of the training experiments: flags, train_and_evaluate, results.json, metrics.jsonl."""
from __future__ import annotations

import contextlib
import dataclasses
import glob
import json
import os
import signal
import sys
import time
from typing import Callable

import jax
from absl import flags
from flax import nnx
from jax.experimental import multihost_utils

from experiments import cli, provenance
from php_jax import call_graph, checkpoint, fitting, flat_lstm, joint, objective, seeds, train
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.task import TrainingDefaults

WORKDIR = flags.DEFINE_string("workdir", None, "Directory for results.json, metrics.jsonl and the model.")
SEED = flags.DEFINE_integer("seed", 0, "Seed for data, initialisation and decoding.")
ITERATIONS = flags.DEFINE_integer("iterations", None, "Adam iterations per level. Default: the task's (the "
                                  "paper's 2000 for its two tasks).")
LEARNING_RATE = flags.DEFINE_float("learning_rate", None, "Adam learning rate. Default: the task's.")
HIDDEN = flags.DEFINE_list("hidden", None, "Hidden layer sizes of every operation/termination MLP. Default: "
                           "the task's.")
ROOT = flags.DEFINE_enum("root", "lstm", list(train.ROOTS), "Network standing in, below the root level, for the "
                         "levels above while they are untrained (the paper's LSTM, or an MLP on each observation).")
TAU_LIMIT = flags.DEFINE_list("tau_limit", None, "Per level (root first), the networks see min(τ, limit) "
                              "instead of the counter τ ('none': τ itself): e.g. 0,1,none. Default: the task's.")
MIN_CAPACITY = flags.DEFINE_list("min_capacity", None, "Per level (root first; the root's is unused), the least "
                                 "counter capacity, for calls longer than the annotated ones. Default: the task's.")
TAU_IN_TERMINATION = flags.DEFINE_list("tau_in_termination", None,
                                       "Per level (root first), whether ψ sees τ: e.g. 0,1,1. Default: task's.")
STRONG_WEIGHT = flags.DEFINE_float("strong_weight", None, "Weight on the strongly supervised loss; default: "
                                   "balanced, num_weak / num_strong (at least 1).")
ROOT_STRONG_WEIGHT = flags.DEFINE_float("root_strong_weight", None, "Weight on the strongly supervised loss at "
                                        "the root level, whose weak views have no latent choice; default: "
                                        "--strong_weight's.")
STRONG_WARMUP = flags.DEFINE_integer("strong_warmup", 0, "Per level below the root, Adam iterations on the strongly "
                                     "supervised demonstrations alone before --iterations on all of them.")
CALL_PENALTY = flags.DEFINE_list("call_penalty", None, "Per level (root first; the root's must be 0), a log-prior "
                                 "cost of each call the stand-in root pushes: weak views' posteriors favour fewer, "
                                 "longer calls. Default: 0 everywhere.")
TRAINING = flags.DEFINE_enum("training", None, list(train.TRAININGS),
                             "levelwise: one level at a time from the lowest, a stand-in root for the levels above "
                             "(the paper); joint: every level at once by exact inference over the whole call stack. "
                             "Default: the task's.")
CALL_GRAPH = flags.DEFINE_enum("call_graph", None, list(call_graph.CALL_GRAPHS),
                               "Which operations each procedure may take. all: any; calls: a procedure the "
                               "annotated demonstrations show calling may call only what they show it calling; "
                               "operations: also, a lowest-level procedure only the elementary action values "
                               "they show it taking (a procedure or value they never show is unrestricted). "
                               "Default: the task's.")
LEVELWISE_ONLY = ("root", "root_strong_weight", "strong_warmup", "call_penalty", "decode")  # unused by joint training
DECODE = flags.DEFINE_enum("decode", "sample", list(objective.DECODERS), "Decoding of weak views for the level above.")
EVAL_EVERY = flags.DEFINE_integer("eval_every", 100, "Iterations between logged losses / root snapshots.")
SNAPSHOT = flags.DEFINE_enum("snapshot", "latest", list(fitting.SNAPSHOT_RULES),
                             "Snapshot kept among those with the best validation accuracy (the PHP root level's, or "
                             "the flat LSTM's).")
DISTRIBUTED = flags.DEFINE_bool("distributed", False, "One of several processes (a multi-host run): "
                                 "jax.distributed.initialize() first, which finds the coordinator, the number of "
                                 "processes and this one's id in the cluster's environment (SLURM, Open MPI, ...) or "
                                 "in JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID. Demonstrations are "
                                 "split over every process's devices; process 0 writes the workdir.")
OVERWRITE = flags.DEFINE_bool("overwrite", False, "Start afresh in a workdir that holds another run (its "
                              "checkpoint, model, metrics and results are deleted); without it such a run is "
                              "resumed if its settings match, and refused if they do not.")
RUN_FILES = (checkpoint.TRAINING_FILE, "metrics.jsonl", "results.json", checkpoint.ARCHITECTURE_FILE,
             checkpoint.MODEL_FILE)
SEEDS_CHECKPOINT = "seeds_checkpoint.msgpack"  # with --seeds, the progress of every seed


class UsageError(ValueError):
  """A flag value the command refuses; the message names the flag."""


def config_from_flags(defaults: TrainingDefaults) -> train.TrainConfig:
  """The TrainConfig the flags ask for, the task's defaults where they are unset. Raises UsageError naming
  the flag of a value that is not allowed."""
  try:
    return _config(defaults)
  except ValueError as e:
    name = str(e).split(" ", 1)[0]
    raise UsageError(f"--{name}: {str(e).split(' ', 1)[1]}" if name.isidentifier() else str(e)) from None


def _config(defaults: TrainingDefaults) -> train.TrainConfig:
  tau = (tuple(_flag_bool(v) for v in TAU_IN_TERMINATION.value) if TAU_IN_TERMINATION.value
         else defaults.tau_in_termination)
  iterations = defaults.iterations if ITERATIONS.value is None else ITERATIONS.value
  if iterations < 1:
    raise ValueError(f"iterations must be a positive integer; got {iterations}")
  learning_rate = defaults.learning_rate if LEARNING_RATE.value is None else LEARNING_RATE.value
  mode = defaults.training if TRAINING.value is None else TRAINING.value
  given = [name for name in LEVELWISE_ONLY if flags.FLAGS[name].present]
  if mode == "joint" and given:
    raise ValueError(joint_refusal(f"{given[0]} applies to level-wise training only") + f" or drop --{given[0]}")
  return train.TrainConfig(iterations=iterations, learning_rate=learning_rate,
                           hidden=tuple(_flag_int("hidden", h) for h in HIDDEN.value) if HIDDEN.value
                           else defaults.hidden,
                           root=ROOT.value,
                           tau_in_termination=tau, strong_weight=STRONG_WEIGHT.value,
                           tau_limit=(tuple(None if v.lower() == "none" else _flag_int("tau_limit", v)
                                            for v in TAU_LIMIT.value) if TAU_LIMIT.value else defaults.tau_limit),
                           min_capacity=(tuple(_flag_int("min_capacity", v) for v in MIN_CAPACITY.value)
                                         if MIN_CAPACITY.value else defaults.min_capacity),
                           root_strong_weight=ROOT_STRONG_WEIGHT.value, strong_warmup=STRONG_WARMUP.value,
                           call_penalty=(tuple(_flag_float("call_penalty", v) for v in CALL_PENALTY.value)
                                         if CALL_PENALTY.value else None),
                           decode=DECODE.value, training=mode,
                           call_graph=defaults.call_graph if CALL_GRAPH.value is None else CALL_GRAPH.value,
                           eval_every=EVAL_EVERY.value, snapshot=SNAPSHOT.value, seed=SEED.value)


def joint_refusal(what: str) -> str:
  """The message refusing `what` in a run that trains jointly, naming where its mode came from."""
  return (f"{what}; this run trains jointly (--training=joint{'' if TRAINING.value else ', the task default'}): "
          "add --training=levelwise")


def _keep_rows(metrics, path: str, count: int) -> float:
  """Truncates the open metrics file (None: only reads it) to its first `count` rows; returns the last kept
  row's "seconds"."""
  with open(path, "rb") as f:
    rows = f.read().splitlines(keepends=True)[:count]
  if metrics:
    metrics.truncate(sum(map(len, rows)))
  return json.loads(rows[-1])["seconds"] if rows else 0.0


def _flag_bool(value: str) -> bool:
  if value.lower() not in ("0", "1", "true", "false", "yes", "no"):
    raise ValueError(f"tau_in_termination values must be 0/1 (or true/false); got {value!r}")
  return value.lower() in ("1", "true", "yes")


def _flag_int(name: str, value: str) -> int:
  try:
    return int(value)
  except ValueError:
    raise ValueError(f"{name} values must be integers; got {value!r}") from None


def _flag_float(name: str, value: str) -> float:
  try:
    return float(value)
  except ValueError:
    raise ValueError(f"{name} values must be numbers; got {value!r}") from None


def train_and_evaluate(task_name: str, spec: HierarchySpec, demos: Demonstration, config: train.TrainConfig,
                       workdir: str, validate: Callable, test: Callable[[object], dict], extra: dict,
                       flat_lstm_hidden: int | None = None) -> dict:
  """Trains a PHP hierarchy level by level (resuming from workdir/checkpoint.msgpack if an earlier run was
  interrupted), or with flat_lstm_hidden the flat LSTM baseline of that many units; saves it, tests it,
  writes results.json; returns the results."""
  _open_workdir(workdir, RUN_FILES)
  config = train.with_strong_weight(config, demos)  # resolved here so that results.json records it
  commit = provenance.code_version()  # the code as it was when the run started
  with _RunLog(workdir) as log:
    if flat_lstm_hidden:
      model, trained = _train_flat_lstm(spec, demos, config, flat_lstm_hidden, validate, log)
      checkpoint.save_flat_lstm(workdir, task_name, model, spec)
    else:
      model, trained, capacity = _train_php(spec, demos, config, validate, log, workdir)
      checkpoint.save_hierarchy(workdir, task_name, model, config.hidden, capacity)
  return _write_results(workdir, {"task": task_name, "model": "flat_lstm" if flat_lstm_hidden else "php",
                                  "config": dataclasses.asdict(config), **extra, **trained},
                        test(model), log.start, commit)


def train_and_evaluate_seeds(task_name: str, spec: HierarchySpec, demos: list[Demonstration],
                             configs: list[train.TrainConfig], workdir: str, validate: list[Callable],
                             test: list[Callable[[object], dict]], extra: list[dict]) -> list[dict]:
  """train_and_evaluate for several seeds' PHP hierarchies, trained level-wise as one program
  (`php_jax.seeds`): seed s's run goes to workdir/seed=S with the files its separate run would write, its
  results.json also naming the seeds trained with it ("trained_with_seeds": its wall time and per-level
  seconds are those of the shared program); the progress of all is checkpointed in
  workdir/seeds_checkpoint.msgpack and resumed from there."""
  workdirs = [os.path.join(workdir, f"seed={c.seed}") for c in configs]
  _open_workdir(workdir, (SEEDS_CHECKPOINT,))
  for run_dir in workdirs:
    _open_workdir(run_dir, RUN_FILES)
  configs = [train.with_strong_weight(c, d) for c, d in zip(configs, demos)]
  commit = provenance.code_version()
  with contextlib.ExitStack() as stack:
    logs = [stack.enter_context(_RunLog(run_dir, {"seed": c.seed})) for run_dir, c in zip(workdirs, configs)]
    trained = seeds.train_seeds(spec, demos, configs, validate, log=lambda s, row: logs[s](row),
                                checkpoint_path=os.path.join(workdir, SEEDS_CHECKPOINT),
                                seed_checkpoint_paths=[os.path.join(w, checkpoint.TRAINING_FILE) for w in workdirs])
    for run_dir, (hierarchy, report) in zip(workdirs, trained):
      checkpoint.save_hierarchy(run_dir, task_name, hierarchy, configs[0].hidden,
                                [report[level]["capacity"] for level in range(spec.num_levels)])
  together = {"trained_with_seeds": [c.seed for c in configs]}  # its times are the shared program's
  return [_write_results(run_dir, {"task": task_name, "model": "php", "config": dataclasses.asdict(c), **e,
                                   **together, **_levels(report)}, t(hierarchy), log.start, commit, {"seed": c.seed})
          for run_dir, c, e, (hierarchy, report), t, log in zip(workdirs, configs, extra, trained, test, logs)]


def _open_workdir(workdir: str, files: tuple[str, ...]) -> None:
  """Makes workdir (refusing a file of that name); with --overwrite, deletes `files` there first; removes
  temporary files a SIGKILL left."""
  if os.path.exists(workdir) and not os.path.isdir(workdir):
    raise UsageError(f"--workdir={workdir} is a file, not a directory")
  if jax.process_index() == 0:  # of several processes (--distributed), the one that writes files
    if OVERWRITE.value:
      for name in files:
        if os.path.exists(os.path.join(workdir, name)):
          os.remove(os.path.join(workdir, name))
    os.makedirs(workdir, exist_ok=True)
    for leftover in glob.glob(os.path.join(workdir, ".*.tmp")):  # a write cut off by SIGKILL
      os.remove(leftover)
  if jax.process_count() > 1:  # the others read the workdir (to resume) once process 0 has cleared it
    multihost_utils.sync_global_devices("workdir ready")


class _RunLog:
  """A run's metrics.jsonl (process 0's) and clock: each row logged gets "seconds" since the run started, is
  appended and printed (with `label` added to the printed copy). A {"resumed": True, "logged": n} row keeps
  the file's first n rows, and the clock goes on from the last of them."""

  def __init__(self, workdir: str, label: dict | None = None):
    self.path, self.label, self.start = os.path.join(workdir, "metrics.jsonl"), label or {}, time.time()
    self.file = None

  def __enter__(self):
    if jax.process_index() == 0:
      self.file = open(self.path, "a")
    return self

  def __exit__(self, *exc):
    if self.file:
      self.file.close()

  def __call__(self, row: dict) -> None:
    if row.get("resumed"):
      self.start -= _keep_rows(self.file, self.path, row["logged"])
    else:
      row = {**row, "seconds": round(time.time() - self.start, 2)}
      if self.file:
        self.file.write(json.dumps(row) + "\n")
        self.file.flush()
    print(json.dumps({**self.label, **row}), flush=True)


def _write_results(workdir: str, results: dict, test_results: dict, start: float, commit,
                   label: dict | None = None) -> dict:
  """results.json: `results` with the test results, wall time, commit and versions; returns it. Prints the
  test results and wall time (with `label`)."""
  results = {**results, "test": test_results, "wall_seconds": round(time.time() - start, 1), "commit": commit,
             "versions": provenance.environment_versions()}
  checkpoint.write_atomically(os.path.join(workdir, "results.json"), json.dumps(results, indent=1).encode())
  print(json.dumps({**(label or {}), "test": test_results, "wall_seconds": results["wall_seconds"]}), flush=True)
  return results


def _train_php(spec: HierarchySpec, demos: Demonstration, config: train.TrainConfig, validate, log, workdir: str):
  """(hierarchy, its results.json entries, capacity per level) by config.training: {"levels": {level: summary}}
  level-wise, {"joint": summary} joint."""
  path = os.path.join(workdir, checkpoint.TRAINING_FILE)
  if config.training == "joint":
    hierarchy, report = joint.train_joint(spec, demos, config, validate, log=log, checkpoint_path=path)
    return hierarchy, {"joint": _summary(report)}, report["capacity"]
  hierarchy, report = train.train_hierarchy(spec, demos, config, validate, log=log, checkpoint_path=path)
  return hierarchy, _levels(report), [report[level]["capacity"] for level in range(spec.num_levels)]


def _levels(report: dict) -> dict:
  """results.json's entry of a level-wise report."""
  return {"levels": {str(level): _summary(entry) for level, entry in report.items()}}


def _summary(entry: dict) -> dict:
  """A training report entry without its loss curve (metrics.jsonl has it), with the final loss."""
  return {k: v for k, v in entry.items() if k != "losses"} | {
      "final_loss": entry["losses"][-1][1] if entry["losses"] else None}


def _train_flat_lstm(spec: HierarchySpec, demos: Demonstration, config: train.TrainConfig, hidden: int, validate,
                     log):
  """The baseline on the same demonstrations' elementary actions (annotations unused), same iterations,
  learning rate, seed and snapshot rule."""
  policy = flat_lstm.FlatLSTMPolicy(spec.obs_dim, spec.action_sizes, hidden,
                                    rngs=nnx.Rngs(config.seed))
  report = flat_lstm.train(policy, demos, config.iterations, config.learning_rate, config.eval_every,
                           on_eval=lambda iteration: validate(policy), log=log, snapshot=config.snapshot)
  return policy, {"flat_lstm": {"hidden": hidden, "best_iteration": report["best_iteration"],
                                "validation": report["validation"], "final_loss": report["losses"][-1][1]}}


def run_resumable(body: Callable[[], object]) -> None:
  """Runs a training command's body (after jax.distributed.initialize() with --distributed): a UsageError or
  CheckpointError ends in one line and exit status 2; Ctrl-C or SIGTERM in one line saying how to resume, and
  exit status 130."""
  if DISTRIBUTED.value:  # before anything uses JAX; JAX reads JAX_COORDINATOR_ADDRESS and the clusters' variables
    jax.distributed.initialize(num_processes=_environment_int("JAX_NUM_PROCESSES"),
                               process_id=_environment_int("JAX_PROCESS_ID"))
  signal.signal(signal.SIGTERM, _interrupt)
  try:
    body()
  except (UsageError, checkpoint.CheckpointError) as e:
    cli.fail(str(e))
  except KeyboardInterrupt:
    print(f"interrupted: {WORKDIR.value} keeps the last checkpoint; rerun the same command to resume",
          file=sys.stderr)
    sys.exit(130)


def _environment_int(name: str) -> int | None:
  value = os.environ.get(name)
  return int(value) if value else None


def _interrupt(signum, frame):
  """SIGTERM ends a run as Ctrl-C does."""
  raise KeyboardInterrupt
