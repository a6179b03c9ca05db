"""What the training commands share: the workdir and model flags, and a run's start and end in one line
(their training settings' flags: `config_flags`)."""
from __future__ import annotations

import os
from typing import Callable

import jax
from absl import flags

from experiments.common import cli, progress, run_report
from experiments.common.config_flags import UsageError
from php_jax import flat
from php_jax.training import checkpoint, recipe, run, selection

WORKDIR = flags.DEFINE_string("workdir", None, "Directory for results.json, metrics.jsonl and the model.")
DISTRIBUTED = flags.DEFINE_bool("distributed", False, "One of several processes (a multi-host run): "
                                 "jax.distributed.initialize() first, which finds the coordinator, the number of "
                                 "processes and this one's id in the cluster's environment (SLURM, Open MPI, ...) or "
                                 "in JAX_COORDINATOR_ADDRESS, JAX_NUM_PROCESSES, JAX_PROCESS_ID. Demonstrations are "
                                 "split over every process's devices; process 0 writes the workdir.")
WAIT = flags.DEFINE_bool("wait", False, "If another run holds the workdir, wait for it to end instead of refusing.")
OVERWRITE = flags.DEFINE_bool("overwrite", False, "Start afresh in a workdir that holds another run (its "
                              "checkpoint, model, metrics and results are deleted); without it such a run is "
                              "resumed if its settings match, and refused if they do not.")
MODEL = flags.DEFINE_enum("model", "php", ["php", *flat.MODEL_CELLS],
                          "php: the hierarchy (--training says how); flat_lstm, flat_gru: a behaviour-cloning "
                          "baseline, an LSTM or a GRU over observations and previous actions.")
FLAT_HIDDEN = flags.DEFINE_integer("flat_hidden", 128, "Hidden units of the flat baseline's LSTM or GRU.")
flags.DEFINE_alias("lstm_hidden", "flat_hidden")
RESTARTS = flags.DEFINE_integer("restarts", None, "Train each of the recipe's candidates from this many "
                                "initialisations and keep the best on the held-out demonstrations: the one that "
                                "explains the most, then the likeliest (docs/training.md, the recipe). Default: "
                                "1; fit: 2 where one or two demonstrations are annotated.", lower_bound=1)
REPORT = flags.DEFINE_bool("report", True, "At the end, write WORKDIR/report.html: settings, results, learning "
                           "curves, call graph and three training demonstrations decoded and drawn (a few seconds).")


def write_report(workdir: str, demos=None, numbers: list[int] | None = None) -> None:
  """With --report, the run's report.html where it is missing or older than its results (`run_report.write`
  says what demos and numbers are)."""
  if REPORT.value:
    written = run_report.write_if_stale(workdir, demos, numbers)
    if written:
      progress.report_written(written)


def flat_model() -> flat.FlatModel | None:
  """The flat baseline --model and --flat_hidden ask for, None for a PHP; UsageError if --flat_hidden is not
  positive, or if --restarts is given to a flat baseline (which has no recipe)."""
  if FLAT_HIDDEN.value < 1:
    raise UsageError(f"--flat_hidden must be a positive integer; got {FLAT_HIDDEN.value}")
  if MODEL.value == "php":
    return None
  if (RESTARTS.value or 1) > 1:
    raise UsageError(f"--restarts applies to PHP hierarchies (not --model={MODEL.value})")
  return flat.FlatModel(flat.MODEL_CELLS[MODEL.value], FLAT_HIDDEN.value)


def run_resumable(body: Callable[[], object]) -> None:
  """Runs a training command's body (after jax.distributed.initialize() with --distributed): a UsageError,
  WorkdirError or CheckpointError ends in one line and exit status 2; Ctrl-C or SIGTERM at once in one line
  saying how to resume, and exit status 130 (`cli.exit_on_interrupt`)."""
  if not WORKDIR.value:
    cli.fail("--workdir: must name a directory; got ''")
  cli.exit_on_interrupt(f"{WORKDIR.value} keeps the last checkpoint; rerun the same command to resume")
  if DISTRIBUTED.value:  # before anything uses JAX; JAX reads JAX_COORDINATOR_ADDRESS and the clusters' variables
    jax.distributed.initialize(num_processes=_environment_int("JAX_NUM_PROCESSES"),
                               process_id=_environment_int("JAX_PROCESS_ID"))
  try:
    body()
  except (UsageError, checkpoint.CheckpointError) as e:
    cli.fail(str(e))
  except run.WorkdirError as e:
    cli.fail(f"--workdir: {e}")
  except OSError as e:  # a full disk or a file system made read-only, found while writing the workdir
    cli.fail(f"{e.filename or WORKDIR.value}: {e.strerror or e}")


def _environment_int(name: str) -> int | None:
  value = os.environ.get(name)
  return int(value) if value else None


def train_php(experiment: run.Experiment, config, given, echo, restarts: int = 1) -> dict:
  """Trains experiment's PHP hierarchy in --workdir by the recipe (`php_jax.training.recipe`) for config,
  whose settings named in `given` were asked for, each candidate from --restarts initialisations (unset: from
  `restarts`); returns its results.json."""
  try:
    chosen = recipe.choose(experiment.spec, experiment.demos, config, given, RESTARTS.value or restarts,
                           experiment.numbers)
  except ValueError as e:
    raise UsageError(f"--restarts: {e}") from None
  return selection.train_and_choose(experiment, config, chosen, WORKDIR.value, OVERWRITE.value, WAIT.value, echo)
