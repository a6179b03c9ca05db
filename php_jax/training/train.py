"""Level-wise Expectation–Gradient training of PHPs (paper §4.2.3): one level at a time, lowest first.

Each level is fitted on its views (`views`) with its EG objective (`objective`); then its weak views are
decoded (Viterbi, per-step max-marginal, or a posterior sample) into the views of the level above. Progress
is checkpointed (`checkpoint`), and a rerun resumes it. Several seeds train as one program (`train_seeds`):
one seed's run is the same loop with S = 1.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import time
from typing import Callable, Sequence

import jax
import numpy as np
from flax import nnx

from php_jax import fitting, sharding
from php_jax.data import agreement, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.demos import validate as validate_demos
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, RootLSTM, RootMLP
from php_jax.training import call_graph, checkpoint, segmentation
from php_jax.training.config import (DISCOVERY_SPLIT_ROUNDS, WEAK_ONLY_ANNEALING, TrainConfig, asks_joint,
                                     check_levels, fields)
from php_jax.training.objective import LevelModel, counter_capacity, decode, level_loss


def train_level(model: LevelModel, view: views.LevelView, capacity: int, config: TrainConfig,
                hooks: fitting.Hooks = fitting.Hooks(), resume: fitting.Progress | None = None) -> fitting.Progress:
  """Full-batch Adam on one level's EG loss over its views in length buckets (`fitting.fit`: snapshots,
  saving, resuming; hooks as fitting.fit takes them). Updates `model` in place. The root level's strong
  weight is config.root_strong_weight when set.

  Below the root level, with config.strong_warmup = W (and both kinds of view present), iterations 1..W fit
  the strong views alone and W+1..W+config.iterations all of them: the weak views' posteriors then start
  from networks that follow the annotated hierarchy instead of from random ones (paper §6: weak views can
  pull the fit towards another hierarchy). The root level's weak views have no latent choice (one procedure,
  τ = step), so it has no warm-up.

  With more than one device, each length bucket is split over all of them (`sharding.data_mesh`)."""
  [progress] = LevelFit([model], [view], [capacity], [config], batched=False).fit(
      hooks.for_models(), None if resume is None else [resume])
  return progress


class LevelFit:
  """One level's fit for S seeds (models[s] on views[s] with capacities[s] and configs[s]; the configs
  differ only in their seed and strong weight): one model's fit (`fitting.fit`), or with batched S models'
  updates as one vmapped program (`fitting.fit_seeds`), their views padded to common shapes
  (`views.stack_seeds`: padding copies weigh 0) and their capacities to the largest, each seed's own
  capacity masking the counters above it (`objective.lattice_inputs`' used_capacity), so that every seed's
  loss and gradients are its separate run's, to float rounding."""

  def __init__(self, models: list[LevelModel], level_views: list[views.LevelView], capacities: list[int],
               configs: list[TrainConfig], batched: bool):
    self.models, self.views, self.capacities, self.configs = models, level_views, capacities, configs
    self.batched, self.is_root = batched, models[0].root is None
    warmups = {warmup_iterations(v, c, self.is_root) for v, c in zip(level_views, configs)}
    if len(warmups) != 1:
      raise ValueError(f"the seeds' strong warm-ups differ ({sorted(warmups)}): some have no strong or no weak "
                       "views at this level")
    self.warmup = warmups.pop()

  def fit(self, hooks: fitting.Hooks, resume: list[fitting.Progress] | None) -> list[fitting.Progress]:
    """The warm-up on the strong views (if any and not done), then every view; hooks and resume as
    `fitting.fit_seeds` takes them (one Progress per seed)."""
    if self.warmup and (resume is None or resume[0].iteration < self.warmup):
      resume = self._fit([views.select(v, v.strong) for v in self.views], self.warmup, hooks, resume)
    return self._fit(self.views, self.warmup + self.configs[0].iterations, hooks, resume)

  def _fit(self, parts: list[views.LevelView], iterations: int, hooks: fitting.Hooks,
           resume: list[fitting.Progress] | None) -> list[fitting.Progress]:
    config, mesh = self.configs[0], sharding.data_mesh()
    weights = [level_strong_weight(c, self.is_root) for c in self.configs]
    schedule = config.schedule(iterations)
    if not self.batched:
      buckets = [views.device_view(b, mesh) for b in views.length_buckets(parts[0], config.length_buckets)]
      capacity = self.capacities[0]
      return [fitting.fit(self.models[0], lambda m, buckets: level_loss(m, buckets, capacity, weights[0]), schedule,
                          hooks.of_first_model(), resume and resume[0], args=(buckets,), mesh=mesh)]
    buckets = views.stack_seeds([views.length_buckets(p, config.length_buckets) for p in parts], mesh)
    weights, used = sharding.replicate((np.asarray(weights, np.float32), np.asarray(self.capacities, np.int32)),
                                       mesh)
    largest = max(self.capacities)
    return fitting.fit_seeds(self.models, lambda model, buckets, weight, used_capacity: level_loss(
        model, buckets, largest, weight, used_capacity), schedule, hooks, resume, args=(buckets, weights, used),
        mesh=mesh)


def level_strong_weight(config: TrainConfig, is_root: bool) -> float:
  """The strong views' weight in a level's loss: config.root_strong_weight at the root level when set."""
  return config.root_strong_weight if is_root and config.root_strong_weight is not None else config.strong_weight


def warmup_iterations(view: views.LevelView, config: TrainConfig, is_root: bool) -> int:
  """Iterations on the strong views alone before those on all (`train_level`): config.strong_warmup below the
  root level where both kinds of view are present, else 0."""
  return config.strong_warmup if not is_root and 0 < view.strong.sum() < len(view.strong) else 0


def level_capacity(view: views.LevelView, level: int, config: TrainConfig) -> int:
  """The root level needs its whole view; below, `objective.counter_capacity` of its strong views' counters
  (config.capacity when nothing is annotated, at least config.min_capacity[level])."""
  if level == 0:
    return int(view.length.max())
  return counter_capacity(view.counters[view.strong], config.capacity,
                          config.min_capacity[level] if config.min_capacity else 0)


def balanced_strong_weight(strong) -> float:
  """num_weak / num_strong (at least 1): strong and weak demonstrations then weigh the same in the loss, so
  a few annotated ones are not outvoted by many weak ones pulling towards another hierarchy (paper §5.2)."""
  num_strong = int(np.sum(strong))
  return max(1.0, (len(strong) - num_strong) / num_strong) if num_strong else 1.0


def make_hierarchy(spec: HierarchySpec, config: TrainConfig, graph: tuple | None = None) -> PHPHierarchy:
  """A freshly initialised hierarchy; graph: its call graph (`call_graph`), None: every call allowed."""
  return PHPHierarchy(spec, hidden=config.hidden, tau_in_termination=config.tau_in_termination,
                      tau_limit=config.tau_limit, allowed_ops=graph, rngs=nnx.Rngs(config.network_seed))


def make_root(spec: HierarchySpec, level: int, config: TrainConfig) -> nnx.Module | None:
  """The root network standing in for the untrained levels above `level` (None for the root level)."""
  if level == 0:
    return None
  rngs = nnx.Rngs(config.network_seed + 1000 + level)
  if config.root == "lstm":
    return RootLSTM(spec.obs_dim, spec.num_procs(level), config.root_hidden, rngs=rngs)
  return RootMLP(spec.obs_dim, spec.num_procs(level), (config.root_hidden,), rngs=rngs)


def prepare(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> TrainConfig:
  """config with the settings that follow the demonstrations resolved (`resolved`), once the settings and the
  demonstrations' annotations are checked against the hierarchy (ValueError naming the first setting, or the
  demonstration and step, that is wrong)."""
  check_levels(spec, config)
  validate_demos(demos, spec)
  return resolved(config, demos, spec)


def resolved(config: TrainConfig, demos: Demonstration, spec: HierarchySpec, flat_lstm: bool = False) -> TrainConfig:
  """config with the settings that follow the demonstrations resolved where unset (as results.json and a
  checkpoint record them): the balanced strong weight (`balanced_strong_weight`); the training mode
  (`training_mode`; levelwise for the flat LSTM, which has no levels); and for a PHP trained jointly on
  demonstrations none of which is annotated, WEAK_ONLY_ANNEALING (else 1: none) and, where spec declares no
  call graph (which says itself which procedure takes which operation) and config.segment_rule applies to
  their actions (`segmentation.read_rule`), the segmentation for half the iterations (else 0), and
  DISCOVERY_SPLIT_ROUNDS of the split search where that rule is "loops" (else 0)."""
  strong = np.asarray(demos.strong)
  strong_weight = balanced_strong_weight(strong) if config.strong_weight is None else config.strong_weight
  training = training_mode(config, bool(strong.any())) if not flat_lstm else config.training or "levelwise"
  weak_only = not flat_lstm and training == "joint" and not strong.any()
  rule = (segmentation.read_rule(demos, config.segment_rule)
          if weak_only and not call_graph.restricts(spec.allowed_ops)
          and None in (config.segment_iterations, config.split_rounds) else None)

  def unset_or(value, default):
    return default if value is None else value

  return dataclasses.replace(
      config, strong_weight=strong_weight, training=training,
      anneal_temperature=unset_or(config.anneal_temperature, WEAK_ONLY_ANNEALING if weak_only else 1.0),
      segment_iterations=unset_or(config.segment_iterations, config.iterations // 2 if rule else 0),
      split_rounds=unset_or(config.split_rounds, DISCOVERY_SPLIT_ROUNDS if rule and rule.name == "loops" else 0))


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
               "joint": "jointly (php_jax.training.train.train_hierarchy trains level-wise)"}


def in_mode(config: TrainConfig, mode: str) -> TrainConfig:
  """config for a trainer of one mode ("levelwise" or "joint"): its training set to mode; ValueError if it
  names the other."""
  if config.training not in (None, mode):
    raise ValueError(f"training: {config.training}; this trains {_TRAINED_BY[mode]}")
  return dataclasses.replace(config, training=mode)


def run_settings(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> dict:
  """What a checkpoint must have been made with to be resumed: the config, the hierarchy and a digest of the
  demonstrations (so another seed, data set or annotation is noticed)."""
  digest = hashlib.sha256()
  for array in demos:
    digest.update(np.ascontiguousarray(np.asarray(array)).tobytes())
  settings = {"config": dataclasses.asdict(config), "levels": spec.levels, "demonstrations": digest.hexdigest(),
              **({"observes": spec.observes} if spec.observes is not None else {})}
  return json.loads(json.dumps(settings))  # as a checkpoint stores it: tuples become lists


# Settings whose default differs from what runs did before the setting existed.
_BEFORE_THEY_EXISTED = {"snapshot": "earliest", "anneal_temperature": 1.0, "training": "levelwise",
                        "segment_iterations": 0, "split_rounds": 0}


def saved_config(saved: dict) -> dict:
  """A config a run recorded (JSON), with every setting it does not name (it predates the setting) as what
  runs did before it: its default, or _BEFORE_THEY_EXISTED's value."""
  return json.loads(json.dumps({**dataclasses.asdict(TrainConfig()), **_BEFORE_THEY_EXISTED, **saved}))


_WHY = {"demonstrations": " (another seed, number of demonstrations or of annotated ones, or data file; the "
                          "balanced strong_weight follows them)", "levels": " (another hierarchy)",
        "observes": " (another hierarchy: what its procedures observe)"}


def check_resumable(path: str, saved_settings: dict, settings: dict) -> None:
  """Raises CheckpointError naming the settings that differ between a checkpoint and this run (a setting the
  checkpoint does not name: `saved_config`)."""
  saved_settings = {**saved_settings, "config": saved_config(saved_settings.get("config", {}))}
  if saved_settings == settings:
    return
  old_config, new_config = saved_settings["config"], settings["config"]
  differ = [f"{k} differ{_WHY[k]}" for k in ("demonstrations", "levels", "observes")
            if saved_settings.get(k) != settings.get(k)]
  differ += [f"{k}: {old_config.get(k)!r} there, {v!r} here" for k, v in new_config.items() if old_config.get(k) != v]
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
  """Trains every level from the lowest to the root, level-wise (config.training unset or "levelwise", else
  ValueError). validate(hierarchy) → validation accuracy, used to pick
  the root level's snapshot. With checkpoint_path, progress is saved there atomically every eval_every
  iterations and an interrupted run resumes from it, ending with the same result as an uninterrupted one (a
  checkpoint made with other settings raises CheckpointError); on resuming, log gets {"resumed": True, ...,
  "logged": n}: the first n rows logged before stay valid, later ones will be logged again. Returns the
  hierarchy and a report (per level: losses, capacity, decoding agreement with the supervisor on weak
  demonstrations, wall time)."""
  store = _Store(checkpoint_path, None, batched=False)
  [trained] = _train_levels(spec, [demos], [config], validate and [validate], lambda s, row: log(row), store)
  return trained


def train_seeds(spec: HierarchySpec, demos: Sequence[Demonstration], configs: Sequence[TrainConfig],
                validate: Sequence[Callable[[PHPHierarchy], float]] | None = None,
                log: Callable[[int, dict], None] = lambda s, row: print(s, row),
                checkpoint_path: str | None = None,
                seed_checkpoint_paths: Sequence[str] | None = None) -> list[tuple[PHPHierarchy, dict]]:
  """train_hierarchy for each seed s (demos[s], configs[s], validate[s]), all at once: per level, their EG
  updates run as one vmapped program (`LevelFit`); decoding and validation run per seed. The configs may
  differ only in their seed and strong weight (the balanced default follows each seed's demonstrations), and
  the seeds need as many length buckets and the same strong warm-up at every level (else ValueError), as the
  training sets of `experiments.train` have (the same numbers of demonstrations and of annotated ones).
  log(s, row) gets seed s's rows, as train_hierarchy's log would (a resumed run first gets {"resumed": True,
  ..., "logged": n} for each seed). With checkpoint_path, progress is saved there (every seed in one file) and
  a rerun resumes it. When training ends, seed_checkpoint_paths[s] gets seed s's finished training
  checkpoint, the file its separate run would leave (its decoded views, for `experiments.segmentation`).
  Returns each seed's (hierarchy, report)."""
  return _train_levels(spec, list(demos), list(configs), validate and list(validate), log,
                       _Store(checkpoint_path, seed_checkpoint_paths, batched=True))


def common_call_graph(spec: HierarchySpec, demos: Sequence[Demonstration],
                      configs: Sequence[TrainConfig]) -> tuple:
  """The call graph every seed's config and demonstrations give (`call_graph.resolve`); ValueError if they
  differ (seeds trained together share one program, so one graph)."""
  graphs = {call_graph.resolve(c.call_graph, d, spec) for d, c in zip(demos, configs)}
  if len(graphs) != 1:
    raise ValueError(f"the seeds' annotated demonstrations show different call graphs ({configs[0].call_graph}); "
                     "train them separately, or allow every operation (call_graph=all)")
  return graphs.pop()


class _Store:
  """Where the level-wise loop keeps its progress: one run's training checkpoint (batched False), or one file
  for every seed's (batched True) and, once training ends, each seed's own file at seed_paths[s]."""

  def __init__(self, path: str | None, seed_paths: Sequence[str] | None, batched: bool):
    self.path, self.seed_paths, self.batched = path, seed_paths, batched

  def read(self, num_seeds: int) -> list[tuple[dict, dict]] | None:
    if not self.batched:
      saved = checkpoint.read_training(self.path)
      return None if saved is None else [saved]
    saved = checkpoint.read_training_seeds(self.path)
    if saved is not None and len(saved) != num_seeds:
      raise checkpoint.CheckpointError(f"{self.path} holds {len(saved)} seeds; this run has {num_seeds}")
    return saved

  def write(self, states: list[tuple], finished: bool) -> None:
    """states: each seed's (hierarchy, meta, progress, decoded), as checkpoint.write_training takes them."""
    if self.path:
      if self.batched:
        checkpoint.write_training_seeds(self.path, states)
      else:
        checkpoint.write_training(self.path, *states[0])
    if finished and self.seed_paths:
      for path, state in zip(self.seed_paths, states):
        checkpoint.write_training(path, *state)


def _train_levels(spec: HierarchySpec, demos: list[Demonstration], configs: list[TrainConfig],
                  validate: list[Callable[[PHPHierarchy], float]] | None, log: Callable[[int, dict], None],
                  store: _Store) -> list[tuple[PHPHierarchy, dict]]:
  """The level-wise loop of train_hierarchy (one seed, not batched) and train_seeds."""
  configs = [prepare(spec, d, in_mode(c, "levelwise")) for d, c in zip(demos, configs)]
  if len({dataclasses.replace(c, seed=0, strong_weight=None) for c in configs}) != 1:
    raise ValueError("seeds trained together must have the same settings but for their seed")
  graph = common_call_graph(spec, demos, configs)
  hierarchies = [make_hierarchy(spec, c, graph) for c in configs]
  settings = [run_settings(spec, d, c) for d, c in zip(demos, configs)]
  reports, decoded = [{} for _ in configs], [{} for _ in configs]
  logs = [CountedLog(lambda row, s=s: log(s, row)) for s in range(len(configs))]
  saved = store.read(len(configs))
  for s, state in enumerate(saved or ()):
    logs[s].resumed(resume_from(store.path, state, settings[s], hierarchies[s]))
    reports[s] = {int(k): v for k, v in state[0]["report"].items()}
    decoded[s] = checkpoint.decoded_views(state)

  def save(level: int, progress: list[fitting.Progress] | None) -> None:
    store.write([(hierarchies[s], {"level": level, "report": reports[s], "settings": settings[s],
                                   "logged": logs[s].logged}, progress and progress[s], decoded[s])
                 for s in range(len(configs))], finished=level == -1)

  level_views = [views.lowest_view(d, spec.num_levels) for d in demos]
  for level in range(spec.num_levels - 1, -1, -1):
    if level not in reports[0]:
      start = time.time()
      in_progress = saved is not None and saved[0][0]["progress"] is not None and saved[0][0]["level"] == level
      models = [level_model(spec, h, level, c) for h, c in zip(hierarchies, configs)]
      fit = LevelFit(models, level_views, [level_capacity(v, level, c) for v, c in zip(level_views, configs)],
                     configs, store.batched)
      resume = [checkpoint.restore_progress(store.path, state, model)
                for state, model in zip(saved, models)] if in_progress else None
      if resume is None:
        for s, (view, capacity) in enumerate(zip(level_views, fit.capacities)):
          logs[s]({"level": level, "capacity": capacity, "view_length": int(view.length.max())})
      on_eval = ((lambda iteration, losses: [v(h) for v, h in zip(validate, hierarchies)])
                 if level == 0 and validate else None)
      hooks = fitting.Hooks(on_eval, lambda s, row, level=level: logs[s]({"level": level, **row}),
                            (lambda progress, level=level: save(level, progress)) if store.path else None)
      progress = fit.fit(hooks, resume)
      for s in range(len(configs)):
        entry, frames = finish_level(demos[s], level_views[s], level, models[s], fit.capacities[s], configs[s],
                                     progress[s])
        if frames is not None:
          decoded[s][level] = frames
        reports[s][level] = {**entry, "seconds": time.time() - start}
      save(level - 1, None)  # the level is complete: its result survives a restart
    elif level == 0 and store.seed_paths:  # finished before: the seeds' own checkpoints may not all be written
      save(-1, None)
    if level > 0:
      level_views = [views.view_above(d, v, level, *decoded[s][level])
                     for s, (d, v) in enumerate(zip(demos, level_views))]
  return list(zip(hierarchies, reports))


def level_model(spec: HierarchySpec, hierarchy: PHPHierarchy, level: int, config: TrainConfig) -> LevelModel:
  """What level `level` trains: the hierarchy's networks of that level and a fresh stand-in root."""
  return LevelModel(hierarchy.levels[level], make_root(spec, level, config),
                    config.call_penalty[level] if config.call_penalty else 0.0)


def finish_level(demos: Demonstration, view: views.LevelView, level: int, model: LevelModel, capacity: int,
                 config: TrainConfig, progress: fitting.Progress) -> tuple[dict, tuple | None]:
  """After a level's fit: its report entry (capacity, losses, snapshot, decoding agreement with the
  supervisor) and, for levels > 0, its view's frames (procedures, counters) [B, T]: annotated where the view
  is strong, decoded where weak."""
  entry = {"capacity": capacity, "losses": progress.losses, "best_iteration": progress.best_iteration,
           "validation": progress.best_score}
  if level == 0:
    return entry, None
  key = jax.random.fold_in(jax.random.key(config.network_seed), level)
  procs, taus = decode(model, view, capacity, config.decode, key)
  known = view.strong[:, None] & (view.procedures != UNKNOWN)  # a strong view's path follows its annotation
  frames = (np.where(known, view.procedures, procs), np.where(known, view.counters, taus))
  counts = agreement.agreement_counts(demos, view, level, *frames)  # counted once for both measures
  entry["decoding_agreement"] = agreement.exact_fraction(*counts)
  entry["relabelled_agreement"] = agreement.relabelled_fraction(*counts)
  return entry, frames
