"""Training settings, written once: every setting's default, meaning and check live on `TrainConfig`'s fields.

A task contributes only overrides (`task.TrainingDefaults`); the training commands generate one flag per field
(`experiments.common.config_flags`), with the field's help and default. `TrainConfig(...)` validates itself and raises
ConfigError naming the field of the first value it refuses; `check_levels` checks the per-level settings
against a hierarchy. The settings that follow the demonstrations where they are left unset (the strong
weight, the training mode, what a run without annotation starts from) are resolved here too (`prepare`,
`resolved`), for the level-wise and the joint trainer alike.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from php_jax import fitting
from php_jax.data import views
from php_jax.demos import Demonstration
from php_jax.demos import validate as validate_demos
from php_jax.hierarchy import HierarchySpec
from php_jax.training import call_graph, objective, segmentation

ROOTS = ("lstm", "mlp")
TRAININGS = ("levelwise", "joint")  # one level at a time (the paper), or every level at once (php_jax.training.joint)


class ConfigError(ValueError):
  """A setting that is not allowed; `field` names it (a flag of the same name on the commands)."""

  def __init__(self, field: str, message: str):
    super().__init__(f"{field}: {message}")
    self.field, self.message = field, message


def _setting(default: Any, help: str, kind: str, choices: tuple[str, ...] = (), levelwise_only: bool = False,
             joint_off: tuple | None = None):
  """A TrainConfig field. kind says how a flag spells it: int, float, str (one of choices), or a per-level list
  (root first) of ints, floats, bools or ints_or_none ('none' for no value). joint_off: for a setting of joint
  training only, the values that leave it off (any other asks for joint training)."""
  return dataclasses.field(default=default, metadata={"help": help, "kind": kind, "choices": choices,
                                                      "levelwise_only": levelwise_only, "joint_off": joint_off})


MAX_SEED = 2**31 - 1
MEMORIES = ("none", "gru")
EPISODE_ENDS = ("root", "environment")
WEAK_ONLY_ANNEALING = 1.5  # the start temperature of joint runs without annotation (RESULTS.md, NanoCraft weak only)
DISCOVERY_SPLIT_ROUNDS = 2  # split-search rounds of joint runs without annotation segmented by loops
FULL_BATCH_MAX = 256  # the most demonstrations an unset batch size trains on whole at every update
DEFAULT_BATCH_SIZE = 64  # an unset batch size above that (docs/training.md, "Minibatches", measures it)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Hyper-parameters of Expectation–Gradient training; the defaults follow the paper where it says."""
  iterations: int = _setting(2000, "Adam iterations per level (level-wise) or in all (joint).", "int")
  learning_rate: float = _setting(3e-3, "Adam learning rate.", "float")
  weight_decay: float = _setting(0.0, "AdamW's decoupled weight decay of every network parameter, per unit "
                                 "learning rate; 0: plain Adam.", "float")
  hidden: tuple[int, ...] = _setting((64, 64), "Hidden layer sizes of every operation and termination network.",
                                     "ints")
  trunk: int | None = _setting(
      None, "Width of each level's shared encoding of the observation (a ReLU layer its procedures' networks "
      "read, computed once per observation for all of them: cheaper where observations are large); unset: "
      "none, each network reads the observation.", "int")
  memory: str = _setting(
      "none", "Each level's memory of the episode: gru, a GRU over the observations and actions so far, whose "
      "state every network of the level reads beside the observation (inference stays exact: the state "
      "depends on what was observed, never on the call stack; joint training only, and each update runs a "
      "sequential pass over every demonstration); none: the networks see the current observation alone.",
      "str", MEMORIES, joint_off=("none",))
  episode_end: str = _setting(
      "root", "How a demonstration ends. root: its root returns after the last action, and training teaches every "
      "frame to stop there (the paper's programs, which end by returning); environment: its environment ended it "
      "(a Gymnasium episode at its goal), so that return is given rather than learned, and a held-out "
      "demonstration counts as replayed once every action is taken.", "str", EPISODE_ENDS)
  root: str = _setting("lstm", "Network standing in, below the root level, for the levels above while they are "
                       "untrained: the paper's LSTM, or an MLP on each observation.", "str", ROOTS, True)
  root_hidden: int = _setting(64, "Hidden units of that stand-in root network.", "int", levelwise_only=True)
  tau_in_termination: tuple[bool, ...] | None = _setting(
      None, "Per level, root first, whether the termination network sees the counter τ (e.g. 0,1,1); unset: "
      "every level.", "bools")
  tau_limit: tuple[int | None, ...] | None = _setting(
      None, "Per level, root first, the networks see min(τ, limit) instead of τ ('none': τ itself), e.g. "
      "0,1,none; unset: τ itself everywhere.", "ints_or_none")
  strong_weight: float | None = _setting(
      None, "Weight on the annotated demonstrations' loss; unset: balanced, num_weak / num_strong (at least 1), "
      "so that a few annotated ones are not outvoted.", "float")
  root_strong_weight: float | None = _setting(
      None, "The same weight at the root level, whose weak views have no latent choice; unset: --strong_weight's.",
      "float", levelwise_only=True)
  strong_warmup: int = _setting(0, "Per level below the root, Adam iterations on the annotated demonstrations "
                                "alone before --iterations on all of them.", "int", levelwise_only=True)
  call_penalty: tuple[float, ...] | None = _setting(
      None, "Per level, root first (the root's 0), a log-prior cost of each call to a procedure of that level (level-"
      "wise: each call the stand-in root pushes): posteriors then favour fewer, longer calls; unset: 0 everywhere.",
      "floats")
  decode: str = _setting("sample", "How weak views are decoded for the level above (the paper sampled).", "str",
                         objective.DECODERS, True)
  capacity: int = _setting(8, "Counter capacity below the root level (joint training: the root's too) where no "
                           "call is annotated; with the segmentation, the most the levels it annotates get.", "int")
  min_capacity: tuple[int, ...] | None = _setting(
      None, "Per level, root first, the least counter capacity (for calls longer than the annotated ones; the "
      "root's is used by joint training only); unset: the longest annotated call decides.", "ints")
  eval_every: int = _setting(100, "Iterations between logged losses, checkpoints and validated snapshots.", "int")
  snapshot: str = _setting("latest", "Which of the equally best-validated snapshots is kept.", "str",
                           fitting.SNAPSHOT_RULES)
  length_buckets: int | None = _setting(
      None, "Demonstrations (level-wise: views) are batched by length into this many buckets, each padded to its "
      "longest, split where they leave the fewest padding steps (a run logs the padded share); unset: the fewest "
      f"from {views.LEAST_BUCKETS} to {views.MOST_BUCKETS} that leave at most {views.MOST_PADDING:.0%} of the "
      f"demonstrations' steps computed as padding ({views.MOST_BUCKETS} where none does).", "int")
  batch_size: int | None = _setting(
      None, "Demonstrations (level-wise: views) per Adam update, drawn afresh at each from every length bucket "
      "in proportion (minibatch Expectation–Gradient: each update's E-step is exact for its demonstrations); "
      f"0: all of them; unset: all of them up to {FULL_BATCH_MAX} demonstrations, {DEFAULT_BATCH_SIZE} above.",
      "int")
  seed: int = _setting(0, "Seed for data, and for initialisation and decoding unless --init_seed is given.", "int")
  init_seed: int | None = _setting(
      None, "Seed for the networks' initialisation and decoding alone, so that restarts share one training set "
      "(--seed's data); unset: --seed.", "int")
  training: str | None = _setting(
      None, "levelwise: one level at a time from the lowest, a stand-in root for the levels above (the paper); "
      "joint: every level at once by exact inference over the whole call stack. A trainer given none trains "
      "jointly where a setting of joint training only is on, or where no demonstration is annotated and no "
      "level-wise setting is given; else level-wise.", "str",
      TRAININGS)
  anneal_temperature: float | None = _setting(
      None, "Joint training: the posterior temperature T ≥ 1 at the first iteration (deterministic annealing): "
      "the loss takes its expectation over call stacks under P(stack | actions)^(1/T), flatter for T > 1, T "
      f"falling linearly to 1 at half the iterations; 1: none; unset: {WEAK_ONLY_ANNEALING} where no "
      "demonstration is annotated (it segments better there; RESULTS.md), else 1.", "float", joint_off=(None, 1))
  segment_iterations: int | None = _setting(
      None, "Joint training: for this many of the first iterations, the demonstrations without annotation take "
      "counters of the lowest levels from the segmentation of their actions that --segment_rule names, as a "
      "partial annotation; 0: none; unset: half of --iterations where no demonstration is annotated, that rule "
      "applies to the actions and the hierarchy declares no call graph, else 0.",
      "int", joint_off=(None, 0))
  segment_rule: str = _setting(
      "loops", "The segmentation --segment_iterations reads off the actions. loops (where some action value "
      "follows itself and another never does): a value that never follows itself ends the call it follows, any "
      "other starts a call, and consecutive calls that start with the same action are one call of the level "
      "above. successors: an action continues the call of the one before it when that value is always followed "
      "by the same one; the lowest level alone.", "str", segmentation.RULES)
  split_rounds: int | None = _setting(
      None, "Joint training: rounds of the split search after the iterations. Each candidate move gives a "
      "procedure that two callers share (or that the root calls at two of its counters) a copy for one of them, "
      "in place of the least-used procedure of its level; every candidate and the unchanged hierarchy train "
      "--split_iterations more, and the one most likely on the validation demonstrations is kept; a round "
      f"that keeps the unchanged one ends the search. unset: {DISCOVERY_SPLIT_ROUNDS} where the loops segmentation "
      "guides training (--segment_rule=loops, --segment_iterations above 0), else 0.", "int", joint_off=(None, 0))
  split_iterations: int = _setting(150, "Adam iterations each candidate of a split-search round trains.", "int",
                                   joint_off=(150,))
  split_hint_iterations: int = _setting(
      50, "Of those, the first iterations of a split by the root's counter, which learn it from the relabelled "
      "most likely level-1 procedures as a partial annotation.", "int", joint_off=(50,))
  call_graph: str = _setting("all", "Which operations each procedure may take. all: any; calls: a procedure the "
                             "annotated demonstrations show calling may call only what they show it calling; "
                             "operations: also, a lowest-level procedure only the elementary action values they "
                             "show it taking (a procedure or value they never show is unrestricted).", "str",
                             call_graph.CALL_GRAPHS)

  @property
  def network_seed(self) -> int:
    """The seed of the networks' initialisation and of decoding: init_seed, else seed."""
    return self.seed if self.init_seed is None else self.init_seed

  def schedule(self, iterations: int | None = None) -> fitting.Schedule:
    """The fit's schedule from these settings: `iterations` updates (default: self.iterations)."""
    return fitting.Schedule(self.iterations if iterations is None else iterations, self.learning_rate,
                            self.eval_every, self.snapshot, weight_decay=self.weight_decay,
                            batch_size=self.batch_size, batch_seed=self.network_seed)

  def __post_init__(self):
    """Raises ConfigError naming the first setting that is not allowed."""
    for name in ("root_hidden", "capacity", "eval_every", "length_buckets"):
      if not (_is_int(getattr(self, name)) and getattr(self, name) >= 1
              or name == "length_buckets" and self.length_buckets is None):
        raise ConfigError(name, f"must be a positive integer; got {getattr(self, name)!r}")
    # 0 iterations: a warm-up alone
    for name in ("iterations", "strong_warmup", "seed", "split_iterations", "split_hint_iterations"):
      if not (_is_int(getattr(self, name)) and getattr(self, name) >= 0):
        raise ConfigError(name, f"must be a non-negative integer; got {getattr(self, name)!r}")
    if self.trunk is not None and not (_is_int(self.trunk) and self.trunk >= 1):
      raise ConfigError("trunk", f"must be a positive integer; got {self.trunk!r}")
    if self.batch_size is not None and not (_is_int(self.batch_size) and self.batch_size >= 0):
      raise ConfigError("batch_size", f"must be a non-negative integer (0: all); got {self.batch_size!r}")
    if self.memory != "none" and self.training == "levelwise":
      raise ConfigError("memory", f"{self.memory} needs joint training (its history reads every elementary step, "
                        "which a level's view leaves out); --training=levelwise was given")
    if self.init_seed is not None and not (_is_int(self.init_seed) and 0 <= self.init_seed):
      raise ConfigError("init_seed", f"must be a non-negative integer; got {self.init_seed!r}")
    for name in ("seed", "init_seed"):
      if (getattr(self, name) or 0) > MAX_SEED:
        raise ConfigError(name, f"must be at most {MAX_SEED} (a 32-bit seed); got {getattr(self, name)}")
    for name in ("learning_rate", "strong_weight", "root_strong_weight"):
      value = getattr(self, name)
      if (value is not None or name == "learning_rate") and not (_is_number(value) and value > 0):
        raise ConfigError(name, f"must be a positive finite number; got {value!r}")
    if not (_is_number(self.weight_decay) and self.weight_decay >= 0):
      raise ConfigError("weight_decay", f"must be a finite number ≥ 0; got {self.weight_decay!r}")
    if self.anneal_temperature is not None and not (_is_number(self.anneal_temperature)
                                                    and self.anneal_temperature >= 1):
      raise ConfigError("anneal_temperature", f"must be a finite number ≥ 1; got {self.anneal_temperature!r}")
    for name in ("segment_iterations", "split_rounds"):
      if getattr(self, name) is not None and not (_is_int(getattr(self, name)) and getattr(self, name) >= 0):
        raise ConfigError(name, f"must be a non-negative integer; got {getattr(self, name)!r}")
    if (self.segment_iterations or 0) > self.iterations:
      raise ConfigError("segment_iterations", f"must be at most --iterations ({self.iterations}); got "
                        f"{self.segment_iterations}")
    if self.split_hint_iterations > self.split_iterations:
      raise ConfigError("split_hint_iterations", f"must be at most --split_iterations ({self.split_iterations}); "
                        f"got {self.split_hint_iterations}")
    joint_asked = [f.name for f in fields() if asks_joint(self, f)]
    if joint_asked and self.training == "levelwise":
      raise ConfigError(joint_asked[0], f"applies to joint training only (training=joint); this config trains "
                        f"{self.training!r}")
    if not (isinstance(self.hidden, tuple) and self.hidden and all(_is_int(h) and h >= 1 for h in self.hidden)):
      raise ConfigError("hidden", f"must list positive layer sizes; got {self.hidden!r}")
    for name, (allowed, what) in _PER_LEVEL.items():
      values = getattr(self, name)
      if values is not None and not (isinstance(values, tuple) and values and all(map(allowed, values))):
        raise ConfigError(name, f"must list one {what} per level, root first; got {values!r}")
    for field in dataclasses.fields(self):
      choices = field.metadata["choices"]
      if choices and getattr(self, field.name) not in choices + ((None,) if field.default is None else ()):
        raise ConfigError(field.name, f"must be one of {', '.join(choices)}; got {getattr(self, field.name)!r}")


def _is_int(x) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def _is_number(x) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool) and math.isfinite(x)


_PER_LEVEL = {  # the per-level settings: each value's check, and its words in a refusal
    "tau_in_termination": (lambda v: isinstance(v, bool), "boolean"),
    "tau_limit": (lambda v: v is None or (_is_int(v) and v >= 0), "non-negative integer or None"),
    "min_capacity": (lambda v: _is_int(v) and v >= 0, "non-negative integer"),
    "call_penalty": (lambda v: _is_number(v) and v >= 0, "finite non-negative number")}


def asks_joint(config: TrainConfig, field: dataclasses.Field) -> bool:
  """Whether config's value of field turns on a setting of joint training only."""
  off = field.metadata["joint_off"]
  return off is not None and getattr(config, field.name) not in off


def fields() -> tuple[dataclasses.Field, ...]:
  """TrainConfig's fields, each with metadata help, kind, choices and levelwise_only (`_setting`)."""
  return dataclasses.fields(TrainConfig)


def check_levels(spec: HierarchySpec, config: TrainConfig) -> None:
  """Raises ConfigError naming the first per-level setting that does not fit the hierarchy's levels."""
  for name in ("tau_in_termination", "tau_limit", "min_capacity"):
    values = getattr(config, name)
    if values is not None and len(values) != spec.num_levels:
      raise ConfigError(name, f"needs one value per level, root first ({spec.num_levels}); got {list(values)}")
  if config.trunk is not None and spec.observes is not None:
    raise ConfigError("trunk", "the hierarchy gives its procedures different observation entries (\"observes\"), "
                      "which one shared encoding cannot respect: drop one or the other")
  if config.call_penalty is not None and (len(config.call_penalty) != spec.num_levels or config.call_penalty[0]):
    raise ConfigError("call_penalty", f"needs one value per level, root first, the root's 0 (it has no stand-in "
                      f"root); got {list(config.call_penalty)} for {spec.num_levels} levels")


def balanced_strong_weight(strong) -> float:
  """num_weak / num_strong (at least 1): strong and weak demonstrations then weigh the same in the loss, so
  a few annotated ones are not outvoted by many weak ones pulling towards another hierarchy (paper §5.2)."""
  num_strong = int(np.sum(strong))
  return max(1.0, (len(strong) - num_strong) / num_strong) if num_strong else 1.0


def prepare(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> TrainConfig:
  """config with the settings that follow the demonstrations resolved (`resolved`), once the settings and the
  demonstrations' annotations are checked against the hierarchy (ValueError naming the first setting, or the
  demonstration and step, that is wrong)."""
  check_levels(spec, config)
  validate_demos(demos, spec)
  return resolved(config, demos, spec)


def resolved(config: TrainConfig, demos: Demonstration, spec: HierarchySpec, flat: bool = False) -> TrainConfig:
  """config with the settings that follow the demonstrations resolved where unset (as results.json and a
  checkpoint record them): the balanced strong weight (`balanced_strong_weight`); the training mode
  (`training_mode`; levelwise for a flat baseline, which has no levels, and no memory of a PHP level's: its
  recurrent cell is its own); and for a PHP trained jointly on
  demonstrations none of which is annotated, WEAK_ONLY_ANNEALING (else 1: none) and, where spec declares no
  call graph (which says itself which procedure takes which operation) and config.segment_rule applies to
  their actions (`segmentation.read_rule`), the segmentation for half the iterations (else 0), and
  DISCOVERY_SPLIT_ROUNDS of the split search where that rule is "loops" and guides training (else 0); the batch size
  (`batch_size_for`); the length buckets (`views.bucket_count` of the demonstrations' lengths)."""
  strong = np.asarray(demos.strong)
  strong_weight = balanced_strong_weight(strong) if config.strong_weight is None else config.strong_weight
  training = training_mode(config, bool(strong.any())) if not flat else config.training or "levelwise"
  memory = "none" if flat else config.memory
  weak_only = not flat and training == "joint" and not strong.any()
  rule = (segmentation.read_rule(demos, config.segment_rule)
          if weak_only and not call_graph.restricts(spec.allowed_ops)
          and None in (config.segment_iterations, config.split_rounds) else None)

  def unset_or(value, default):
    return default if value is None else value

  segment_iterations = unset_or(config.segment_iterations, config.iterations // 2 if rule else 0)
  return dataclasses.replace(
      config, strong_weight=strong_weight, training=training, memory=memory,
      anneal_temperature=unset_or(config.anneal_temperature, WEAK_ONLY_ANNEALING if weak_only else 1.0),
      segment_iterations=segment_iterations,
      split_rounds=unset_or(config.split_rounds, DISCOVERY_SPLIT_ROUNDS
                            if rule and rule.name == "loops" and segment_iterations else 0),
      batch_size=batch_size_for(config, len(strong)),
      length_buckets=config.length_buckets or views.bucket_count(demos.length))


def with_common_buckets(configs: list[TrainConfig]) -> list[TrainConfig]:
  """Resolved configs of seeds trained together, each with the most length buckets any of them resolved to:
  their buckets are stacked one on another (`views.stack_seeds`)."""
  count = max(c.length_buckets for c in configs)
  return [dataclasses.replace(c, length_buckets=count) for c in configs]


def batch_size_for(config: TrainConfig, num_demos: int) -> int:
  """config.batch_size, or where unset: 0 (all) for at most FULL_BATCH_MAX demonstrations, else
  DEFAULT_BATCH_SIZE. A full-batch update's cost grows with the demonstrations, a minibatch's does not."""
  if config.batch_size is not None:
    return config.batch_size
  return 0 if num_demos <= FULL_BATCH_MAX else DEFAULT_BATCH_SIZE


def training_mode(config: TrainConfig, annotated: bool) -> str:
  """config.training, or where unset: "joint" if a setting of joint training only is on (`asks_joint`), or
  if no demonstration is annotated and every level-wise-only setting is at its default; else "levelwise"."""
  if config.training is not None:
    return config.training
  levelwise_asked = any(getattr(config, f.name) != f.default for f in fields() if f.metadata["levelwise_only"])
  if any(asks_joint(config, f) for f in fields()) or not (annotated or levelwise_asked):
    return "joint"
  return "levelwise"


_TRAINED_BY = {"levelwise": "level-wise (php_jax.training.joint.train_joint trains jointly)",
               "joint": "jointly (php_jax.training.levelwise.train_hierarchy trains level-wise)"}


def in_mode(config: TrainConfig, mode: str) -> TrainConfig:
  """config for a trainer of one mode ("levelwise" or "joint"): its training set to mode; ValueError if it
  names the other."""
  if config.training not in (None, mode):
    raise ValueError(f"training: {config.training}; this trains {_TRAINED_BY[mode]}")
  return dataclasses.replace(config, training=mode)
