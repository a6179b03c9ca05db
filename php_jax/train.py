"""Level-wise Expectation–Gradient training of PHPs (paper §4.2.3): one level at a time, lowest first.

Each level is fitted on its views (`views`) with its EG objective (`objective`); then its weak views are
decoded (Viterbi, per-step max-marginal, or a posterior sample) into the views of the level above. Progress
is checkpointed (`checkpoint`), and a rerun resumes it.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import time
from typing import Callable

import jax
import numpy as np
from flax import nnx

from php_jax import agreement, call_graph, checkpoint, fitting, sharding, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.demos import validate as validate_demos
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, RootLSTM, RootMLP
from php_jax.objective import DECODERS, LevelModel, decode, level_loss


ROOTS = ("lstm", "mlp")
TRAININGS = ("levelwise", "joint")  # one level at a time (the paper), or every level at once (php_jax.joint)


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Hyper-parameters of level-wise EG training (defaults follow the paper where it says)."""
  iterations: int = 2000            # per level, as in the paper
  learning_rate: float = 3e-3
  hidden: tuple[int, ...] = (64, 64)
  root: str = "lstm"                # network standing in for untrained levels: "lstm" or "mlp"
  root_hidden: int = 64
  tau_in_termination: tuple[bool, ...] | None = None  # per level; None: all True
  tau_limit: tuple[int | None, ...] | None = None  # per level, the networks see min(τ, limit); None: no limit
  strong_weight: float | None = None  # weight on strongly supervised demonstrations' loss; None: balanced
  root_strong_weight: float | None = None  # the root level's: its weak views have no latent choice; None: the same
  strong_warmup: int = 0            # below the root, iterations on the strong views alone before those on all
  call_penalty: tuple[float, ...] | None = None  # per level (root first), log-prior cost of each call; None: 0
  decode: str = "sample"            # how weak views are decoded for the level above (the paper sampled)
  capacity: int = 8                 # counter capacity C below the root level when nothing is annotated
  min_capacity: tuple[int, ...] | None = None  # per level, the least C below the root (calls may be longer
                                               # than the annotated ones)
  eval_every: int = 100             # logging, checkpoint and root-snapshot interval
  snapshot: str = "latest"          # root snapshot among the equally best-validated: "latest" or "earliest"
  length_buckets: int = 4           # views are batched by length into this many buckets
  seed: int = 0
  training: str = "levelwise"       # TRAININGS
  call_graph: str = "all"           # call_graph.CALL_GRAPHS: any operation, or the annotated calls (and actions)

  def __post_init__(self):
    """Raises ValueError naming the first setting that is not allowed."""
    for name in ("root_hidden", "capacity", "eval_every", "length_buckets"):
      if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 1):
        raise ValueError(f"{name} must be a positive integer; got {getattr(self, name)!r}")
    for name in ("iterations", "strong_warmup"):  # 0 iterations: a warm-up alone
      if not (isinstance(getattr(self, name), int) and getattr(self, name) >= 0):
        raise ValueError(f"{name} must be a non-negative integer; got {getattr(self, name)!r}")
    if not (math.isfinite(self.learning_rate) and self.learning_rate > 0):
      raise ValueError(f"learning_rate must be a positive finite number; got {self.learning_rate!r}")
    if not (self.hidden and all(isinstance(h, int) and h >= 1 for h in self.hidden)):
      raise ValueError(f"hidden must list positive layer sizes; got {self.hidden!r}")
    for name in ("strong_weight", "root_strong_weight"):
      value = getattr(self, name)
      if value is not None and not (math.isfinite(value) and value > 0):
        raise ValueError(f"{name} must be a positive finite number; got {value!r}")
    if self.tau_limit is not None and not all(v is None or (isinstance(v, int) and v >= 0) for v in self.tau_limit):
      raise ValueError(f"tau_limit values must be non-negative integers or None; got {self.tau_limit!r}")
    if self.min_capacity is not None and not all(isinstance(v, int) and v >= 0 for v in self.min_capacity):
      raise ValueError(f"min_capacity values must be non-negative integers; got {self.min_capacity!r}")
    if self.call_penalty is not None and not all(math.isfinite(v) and v >= 0 for v in self.call_penalty):
      raise ValueError(f"call_penalty values must be finite and non-negative; got {self.call_penalty!r}")
    for name, allowed in (("root", ROOTS), ("decode", DECODERS), ("snapshot", fitting.SNAPSHOT_RULES),
                          ("training", TRAININGS), ("call_graph", call_graph.CALL_GRAPHS)):
      if getattr(self, name) not in allowed:
        raise ValueError(f"{name} must be one of {', '.join(allowed)}; got {getattr(self, name)!r}")


def train_level(model: LevelModel, view: views.LevelView, capacity: int, config: TrainConfig,
                on_eval: Callable[[int, float], float | None] | None = None,
                log: Callable[[dict], None] = print, resume: fitting.Progress | None = None,
                save: Callable[[fitting.Progress], None] | None = None) -> fitting.Progress:
  """Full-batch Adam on one level's EG loss over its views in length buckets (`fitting.fit`: snapshots,
  saving, resuming). Updates `model` in place. The root level's strong weight is config.root_strong_weight
  when set.

  Below the root level, with config.strong_warmup = W (and both kinds of view present), iterations 1..W fit
  the strong views alone and W+1..W+config.iterations all of them: the weak views' posteriors then start
  from networks that follow the annotated hierarchy instead of from random ones (paper §6: weak views can
  pull the fit towards another hierarchy). The root level's weak views have no latent choice (one procedure,
  τ = step), so it has no warm-up.

  With more than one device, each length bucket is split over all of them (`sharding.data_mesh`)."""
  strong_weight = level_strong_weight(config, model.root is None)
  mesh = sharding.data_mesh()

  def fit(part: views.LevelView, iterations: int, progress: fitting.Progress | None) -> fitting.Progress:
    buckets = [views.device_view(b, mesh) for b in views.length_buckets(part, config.length_buckets)]
    return fitting.fit(model, lambda m, buckets: level_loss(m, buckets, capacity, strong_weight), iterations,
                       config.learning_rate, config.eval_every, on_eval, log, progress, save, config.snapshot,
                       args=(buckets,), mesh=mesh)

  warmup = warmup_iterations(view, config, model.root is None)
  if warmup and (resume is None or resume.iteration < warmup):
    resume = fit(views.select(view, view.strong), warmup, resume)
  return fit(view, warmup + config.iterations, resume)


def level_strong_weight(config: TrainConfig, is_root: bool) -> float:
  """The strong views' weight in a level's loss: config.root_strong_weight at the root level when set."""
  return config.root_strong_weight if is_root and config.root_strong_weight is not None else config.strong_weight


def warmup_iterations(view: views.LevelView, config: TrainConfig, is_root: bool) -> int:
  """Iterations on the strong views alone before those on all (`train_level`): config.strong_warmup below the
  root level where both kinds of view are present, else 0."""
  return config.strong_warmup if not is_root and 0 < view.strong.sum() < len(view.strong) else 0


def level_capacity(view: views.LevelView, level: int, config: TrainConfig) -> int:
  """The root level needs its whole view; below, the longest annotated call (the cells the networks are
  evaluated on scale with C), or config.capacity when nothing is annotated, and at least
  config.min_capacity[level]."""
  if level == 0:
    return int(view.length.max())
  annotated = view.counters[view.strong][view.counters[view.strong] >= 0]
  capacity = int(annotated.max()) + 1 if annotated.size else config.capacity
  return max(capacity, config.min_capacity[level]) if config.min_capacity else capacity


def balanced_strong_weight(strong) -> float:
  """num_weak / num_strong (at least 1): strong and weak demonstrations then weigh the same in the loss, so
  a few annotated ones are not outvoted by many weak ones pulling towards another hierarchy (paper §5.2)."""
  num_strong = int(np.sum(strong))
  return max(1.0, (len(strong) - num_strong) / num_strong) if num_strong else 1.0


def make_hierarchy(spec: HierarchySpec, config: TrainConfig, graph: tuple | None = None) -> PHPHierarchy:
  """A freshly initialised hierarchy; graph: its call graph (`call_graph`), None: every call allowed."""
  return PHPHierarchy(spec, hidden=config.hidden, tau_in_termination=config.tau_in_termination,
                      tau_limit=config.tau_limit, allowed_ops=graph, rngs=nnx.Rngs(config.seed))


def make_root(spec: HierarchySpec, level: int, config: TrainConfig) -> nnx.Module | None:
  """The root network standing in for the untrained levels above `level` (None for the root level)."""
  if level == 0:
    return None
  rngs = nnx.Rngs(config.seed + 1000 + level)
  if config.root == "lstm":
    return RootLSTM(spec.obs_dim, spec.num_procs(level), config.root_hidden, rngs=rngs)
  return RootMLP(spec.obs_dim, spec.num_procs(level), (config.root_hidden,), rngs=rngs)


def check_config(spec: HierarchySpec, config: TrainConfig) -> None:
  """Raises ValueError naming the first per-level setting that does not fit the hierarchy."""
  for name in ("tau_in_termination", "tau_limit", "min_capacity"):
    values = getattr(config, name)
    if values is not None and len(values) != spec.num_levels:
      raise ValueError(f"{name} needs one value per level, root first ({spec.num_levels}); got {values}")
  if config.call_penalty is not None and (len(config.call_penalty) != spec.num_levels or config.call_penalty[0]):
    raise ValueError(f"call_penalty needs one value per level, root first, the root's 0 (it has no stand-in root); "
                     f"got {config.call_penalty} for {spec.num_levels} levels")


def prepare(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> TrainConfig:
  """config with its strong weight resolved, once the settings and the demonstrations' annotations are checked
  against the hierarchy (ValueError naming the first setting, or the demonstration and step, that is wrong)."""
  check_config(spec, config)
  validate_demos(demos, spec)
  return with_strong_weight(config, demos)


def with_strong_weight(config: TrainConfig, demos: Demonstration) -> TrainConfig:
  """config with its strong weight resolved: the balanced one (`balanced_strong_weight`) where unset."""
  if config.strong_weight is not None:
    return config
  return dataclasses.replace(config, strong_weight=balanced_strong_weight(np.asarray(demos.strong)))


def run_settings(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> dict:
  """What a checkpoint must have been made with to be resumed: the config, the hierarchy and a digest of the
  demonstrations (so another seed, data set or annotation is noticed)."""
  digest = hashlib.sha256()
  for array in demos:
    digest.update(np.ascontiguousarray(np.asarray(array)).tobytes())
  settings = {"config": dataclasses.asdict(config), "levels": spec.levels, "demonstrations": digest.hexdigest()}
  return json.loads(json.dumps(settings))  # as a checkpoint stores it: tuples become lists


_BEFORE_THEY_EXISTED = {"snapshot": "earliest"}  # settings whose default differs from what runs did before them


def check_resumable(path: str, saved_settings: dict, settings: dict) -> None:
  """Raises CheckpointError naming the settings that differ between a checkpoint and this run. A setting the
  checkpoint does not name (it predates the setting) counts as what runs did before it: its default, or
  _BEFORE_THEY_EXISTED's value."""
  defaults = json.loads(json.dumps({**dataclasses.asdict(TrainConfig()), **_BEFORE_THEY_EXISTED}))
  saved_settings = {**saved_settings, "config": {**defaults, **saved_settings.get("config", {})}}
  if saved_settings == settings:
    return
  old_config, new_config = saved_settings["config"], settings["config"]
  differ = [f"{k}: {old_config.get(k)!r} there, {v!r} here" for k, v in new_config.items() if old_config.get(k) != v]
  differ += [f"{k} differ" for k in ("levels", "demonstrations") if saved_settings.get(k) != settings[k]]
  raise checkpoint.CheckpointError(f"{path} was made with other settings ({'; '.join(differ) or 'unknown'}); "
                                   "use a fresh workdir, or --overwrite to start again")


def resume_from(path: str, saved: tuple[dict, dict], settings: dict, hierarchy: PHPHierarchy) -> dict:
  """Restores a read training checkpoint's parameters into hierarchy once its settings are this run's
  (else CheckpointError naming those that differ); returns the row a resumed run logs first."""
  meta = saved[0]
  check_resumable(path, meta.get("settings", {}), settings)
  checkpoint.restore_hierarchy(path, saved, hierarchy)
  return {"resumed": True, "level": meta["level"], "iteration": meta["progress"] and meta["progress"]["iteration"],
          "logged": meta["logged"]}


class CountedLog:
  """log(row), counting the rows: a checkpoint records how many were logged before it, so that a resumed
  run knows which rows of its metrics stay valid."""

  def __init__(self, log: Callable[[dict], None]):
    self.log, self.logged = log, 0

  def __call__(self, row: dict) -> None:
    self.logged += 1
    self.log(row)

  def resumed(self, row: dict) -> None:
    """Logs a resume_from row (not counted: the rows logged before it are)."""
    self.logged = row["logged"]
    self.log(row)


def train_hierarchy(spec: HierarchySpec, demos: Demonstration, config: TrainConfig,
                    validate: Callable[[PHPHierarchy], float] | None = None,
                    log: Callable[[dict], None] = print,
                    checkpoint_path: str | None = None) -> tuple[PHPHierarchy, dict]:
  """Trains every level from the lowest to the root. validate(hierarchy) → validation accuracy, used to pick
  the root level's snapshot. With checkpoint_path, progress is saved there atomically every eval_every
  iterations and an interrupted run resumes from it, ending with the same result as an uninterrupted one (a
  checkpoint made with other settings raises CheckpointError); on resuming, log gets {"resumed": True, ...,
  "logged": n}: the first n rows logged before stay valid, later ones will be logged again. Returns the
  hierarchy and a report (per level: losses, capacity, decoding agreement with the supervisor on weak
  demonstrations, wall time)."""
  config = prepare(spec, demos, config)
  hierarchy = make_hierarchy(spec, config, call_graph.resolve(config.call_graph, demos, spec))
  settings = run_settings(spec, demos, config)
  saved = checkpoint.read_training(checkpoint_path)
  report, decoded, counted_log = {}, {}, CountedLog(log)
  if saved is not None:
    counted_log.resumed(resume_from(checkpoint_path, saved, settings, hierarchy))
    report = {int(k): v for k, v in saved[0]["report"].items()}
    decoded = checkpoint.decoded_views(saved)

  def save(level: int, progress: fitting.Progress | None) -> None:
    if checkpoint_path:
      checkpoint.write_training(checkpoint_path, hierarchy, {"level": level, "report": report,
                                                             "settings": settings, "logged": counted_log.logged},
                                progress, decoded)

  view = views.lowest_view(demos, spec.num_levels)
  for level in range(spec.num_levels - 1, -1, -1):
    if level not in report:
      in_progress = saved is not None and saved[0]["progress"] is not None and saved[0]["level"] == level
      report[level] = _train_one_level(spec, demos, view, level, hierarchy, config, validate, counted_log, decoded,
                                       lambda progress, level=level: save(level, progress),
                                       saved if in_progress else None, checkpoint_path)
      save(level - 1, None)  # the level is complete: its result survives a restart
    if level > 0:
      view = views.view_above(demos, view, level, *decoded[level])
  return hierarchy, report


def _train_one_level(spec, demos, view, level, hierarchy, config, validate, log, decoded, save, saved,
                     checkpoint_path) -> dict:
  """Fits one level (resuming `saved` if given), decodes its weak views into decoded[level]; its report."""
  start = time.time()
  capacity = level_capacity(view, level, config)
  model = level_model(spec, hierarchy, level, config)
  resume = checkpoint.restore_progress(checkpoint_path, saved, model) if saved is not None else None
  on_eval = (lambda it, loss: validate(hierarchy)) if (level == 0 and validate) else None
  if resume is None:
    log({"level": level, "capacity": capacity, "view_length": int(view.length.max())})
  progress = train_level(model, view, capacity, config, on_eval,
                         log=lambda row: log({"level": level, **row}), resume=resume,
                         save=save if checkpoint_path else None)
  return finish_level(demos, view, level, model, capacity, config, progress, decoded, start)


def level_model(spec: HierarchySpec, hierarchy: PHPHierarchy, level: int, config: TrainConfig) -> LevelModel:
  """What level `level` trains: the hierarchy's networks of that level and a fresh stand-in root."""
  return LevelModel(hierarchy.levels[level], make_root(spec, level, config),
                    config.call_penalty[level] if config.call_penalty else 0.0)


def finish_level(demos: Demonstration, view: views.LevelView, level: int, model: LevelModel, capacity: int,
                 config: TrainConfig, progress: fitting.Progress, decoded: dict, start: float) -> dict:
  """After a level's fit: decodes its weak views into decoded[level] (levels > 0); returns the level's report
  entry (capacity, losses, snapshot, decoding agreement with the supervisor, seconds since `start`)."""
  entry = {"capacity": capacity, "losses": progress.losses, "best_iteration": progress.best_iteration,
           "validation": progress.best_score}
  if level > 0:
    key = jax.random.fold_in(jax.random.key(config.seed), level)
    procs, taus = decode(model, view, capacity, config.decode, key)
    known = view.strong[:, None] & (view.procedures != UNKNOWN)  # a strong view's path follows its annotation
    decoded[level] = (np.where(known, view.procedures, procs), np.where(known, view.counters, taus))
    counts = agreement.agreement_counts(demos, view, level, *decoded[level])  # counted once for both measures
    entry["decoding_agreement"] = agreement.exact_fraction(*counts)
    entry["relabelled_agreement"] = agreement.relabelled_fraction(*counts)
  entry["seconds"] = time.time() - start
  return entry
