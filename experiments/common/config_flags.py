"""Training settings on the command line: one flag per field of `php_jax.training.config.TrainConfig` (its name, help,
choices and default), parsed into the TrainConfig the flags ask for. Defines no flag of its own: each
command calls `define_config_flags`."""
from __future__ import annotations

from typing import Callable

from absl import flags

from php_jax.training import call_graph
from php_jax.training import config as config_lib


class UsageError(ValueError):
  """A flag value the command refuses; the message names the flag."""


def define_config_flags(defaults: Callable[[str, object], str], flag_values: flags.FlagValues = flags.FLAGS) -> None:
  """One flag per TrainConfig field (`php_jax.training.config`), with the field's name, help and choices; its help ends
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
  allowed, or of a level-wise setting given to a joint run or beside a setting of joint training only."""
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
  joint_on = [f for f in config_lib.fields() if config_lib.asks_joint(config, f)]
  if config.training is None and given and joint_on:
    field = joint_on[0]
    setting = (f"--{field.name}={flag_values[field.name].value}" if flag_values[field.name].present else
               f"{field.name} {getattr(config, field.name)} (this command's default here)")
    raise UsageError(f"--{given[0]}: applies to level-wise training only, and {setting} to joint training only: "
                     f"drop one of them, or give --training")
  return config


def given_settings(overrides: dict, flag_values: flags.FlagValues = flags.FLAGS) -> frozenset[str]:
  """The TrainConfig fields asked for: by a flag, or in overrides (a task's or a hierarchy file's). The recipe
  chooses the others (`php_jax.training.recipe`)."""
  return frozenset(overrides) | {f.name for f in config_lib.fields() if flag_values[f.name].value is not None}


def check_levels(spec, config: config_lib.TrainConfig) -> None:
  """config_lib.check_levels, a refusal naming the flag."""
  try:
    config_lib.check_levels(spec, config)
  except config_lib.ConfigError as e:
    raise UsageError(f"--{e.field}: {e.message}") from None


def check_call_graph(config: config_lib.TrainConfig, demos, spec, where: str) -> None:
  """Refuses a --call_graph that leaves some step of demos to no procedure (`call_graph.resolve`): a
  UsageError starting with where (the demonstrations' flag, or the call graph's)."""
  try:
    call_graph.resolve(config.call_graph, demos, spec)
  except ValueError as e:  # demonstrations are numbered from 0 in their order
    raise UsageError(f"{where}: {e}") from None


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
