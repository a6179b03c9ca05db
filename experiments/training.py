"""What the training commands share: their flags (one per training setting, generated from
`php_jax.config.TrainConfig`), the configuration the flags ask for, and a run's start and end in one line."""
from __future__ import annotations

import os
import signal
import sys
from typing import Callable

import jax
from absl import flags

from experiments import cli
from php_jax import checkpoint, run
from php_jax import config as config_lib

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


class UsageError(ValueError):
  """A flag value the command refuses; the message names the flag."""


def define_config_flags(defaults: Callable[[str, object], str], flag_values: flags.FlagValues = flags.FLAGS) -> None:
  """One flag per TrainConfig field (`php_jax.config`), with the field's name, help and choices; its help ends
  with defaults(name, TrainConfig's default), the command's own words for the default (a task's or a
  hierarchy file's may differ; none where empty). Unset flags are None."""
  for field in config_lib.fields():
    meta, default = field.metadata, defaults(field.name, field.default)
    help_text = f"{meta['help']} Default: {default}." if default else meta["help"]
    if meta["kind"] == "int":
      flags.DEFINE_integer(field.name, None, help_text, flag_values=flag_values)
    elif meta["kind"] == "float":
      flags.DEFINE_float(field.name, None, help_text, flag_values=flag_values)
    elif meta["choices"]:
      flags.DEFINE_enum(field.name, None, list(meta["choices"]), help_text, flag_values=flag_values)
    else:
      flags.DEFINE_list(field.name, None, help_text, flag_values=flag_values)


def default_text(value, overrides: dict[str, object] | None = None) -> str:
  """A setting's default as --help shows it: the value as a flag spells it (64,64 for a tuple; '' for None,
  whose help says what unset means), then overrides {whose: value} in parentheses."""
  if overrides:
    others = "; ".join(f"{who}: {default_text(v) or 'unset'}" for who, v in overrides.items())
    return f"{default_text(value) or 'unset'} ({others})"
  if value is None:
    return ""
  if isinstance(value, tuple):
    return ",".join("none" if v is None else str(int(v)) if isinstance(v, bool) else str(v) for v in value)
  return str(value)


def config_from_flags(overrides: dict, flag_values: flags.FlagValues = flags.FLAGS) -> config_lib.TrainConfig:
  """The TrainConfig the flags ask for: each field from its flag where given, else from overrides (a task's or
  a hierarchy file's), else TrainConfig's default. Raises UsageError naming the flag of a value that is not
  allowed, or of a level-wise setting given to a joint run."""
  values = dict(overrides)
  for field in config_lib.fields():
    value = flag_values[field.name].value
    if value is not None:
      values[field.name] = _parse(field, value)
  try:
    config = config_lib.TrainConfig(**values)
  except config_lib.ConfigError as e:
    raise UsageError(f"--{e.field}: {e.message}") from None
  if config.iterations < 1:  # the library allows 0 (a strong warm-up alone); a command trains
    raise UsageError(f"--iterations: must be a positive integer; got {config.iterations}")
  given = [f.name for f in config_lib.fields() if f.metadata["levelwise_only"] and flag_values[f.name].present]
  if config.training == "joint" and given:
    raise UsageError(joint_refusal(f"--{given[0]}: applies to level-wise training only", flag_values)
                     + f" or drop --{given[0]}")
  return config


def check_levels(spec, config: config_lib.TrainConfig) -> None:
  """config_lib.check_levels, a refusal naming the flag."""
  try:
    config_lib.check_levels(spec, config)
  except config_lib.ConfigError as e:
    raise UsageError(f"--{e.field}: {e.message}") from None


def _parse(field, value):
  """A flag's value as the field's type (a list flag's strings parsed per its kind); UsageError naming it."""
  kind = field.metadata["kind"]
  if kind in ("int", "float", "str"):
    return value
  words = {"ints": "integers", "floats": "numbers", "bools": "0/1 (or true/false)",
           "ints_or_none": "integers or 'none'"}[kind]
  try:
    if not value:
      raise ValueError
    return tuple(_parse_one(kind, v) for v in value)
  except ValueError:
    raise UsageError(f"--{field.name} must list {words}; got {','.join(value)!r}") from None


def _parse_one(kind: str, text: str):
  if kind == "bools":
    if text.lower() not in ("0", "1", "true", "false", "yes", "no"):
      raise ValueError(text)
    return text.lower() in ("1", "true", "yes")
  if kind == "ints_or_none" and text.lower() == "none":
    return None
  return float(text) if kind == "floats" else int(text)


def joint_refusal(what: str, flag_values: flags.FlagValues = flags.FLAGS) -> str:
  """The message refusing `what` in a run that trains jointly, naming where its mode came from."""
  given = flag_values["training"].present
  return f"{what}; this run trains jointly (--training=joint{'' if given else ', the task default'}): " \
         "add --training=levelwise"


def run_resumable(body: Callable[[], object]) -> None:
  """Runs a training command's body (after jax.distributed.initialize() with --distributed): a UsageError or
  CheckpointError ends in one line and exit status 2; Ctrl-C or SIGTERM in one line saying how to resume, and
  exit status 130."""
  if DISTRIBUTED.value:  # before anything uses JAX; JAX reads JAX_COORDINATOR_ADDRESS and the clusters' variables
    jax.distributed.initialize(num_processes=_environment_int("JAX_NUM_PROCESSES"),
                               process_id=_environment_int("JAX_PROCESS_ID"))
  if not WORKDIR.value:
    cli.fail("--workdir: must name a directory; got ''")
  signal.signal(signal.SIGTERM, _interrupt)
  try:
    body()
  except (UsageError, checkpoint.CheckpointError) as e:
    cli.fail(str(e))
  except run.WorkdirError as e:
    cli.fail(f"--workdir: {e}")
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
