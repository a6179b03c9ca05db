"""Level-wise Expectation–Gradient training of PHPs (paper §4.2.3): one level at a time, lowest first.

Each level is fitted on its views (`views`) with its EG objective (`objective`); then its weak views are
decoded (Viterbi, per-step max-marginal, or a posterior sample) into the views of the level above. Progress
is checkpointed (`resume`), and a rerun resumes it. Several seeds train as one program (`train_seeds`):
one seed's run is the same loop with S = 1.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import jax
import numpy as np

from php_jax import fitting, sharding
from php_jax.data import agreement, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import call_graph
from php_jax.training.resume import (CheckpointError, CountedLog, decoded_views, read_training, read_training_seeds,
                                     restore_progress, resume_from, run_settings, write_training,
                                     write_training_seeds)
from php_jax.training.config import TrainConfig, in_mode, prepare, with_common_buckets
from php_jax.training.networks import make_hierarchy, make_root
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
      buckets = views.training_buckets(parts[0], config.length_buckets, mesh)
      capacity = self.capacities[0]
      return [fitting.fit(self.models[0], lambda m, buckets: level_loss(m, buckets, capacity, weights[0]), schedule,
                          hooks.of_first_model(), resume and resume[0], args=(buckets,), mesh=mesh)]
    buckets = views.stack_seeds([views.length_buckets(p, config.length_buckets) for p in parts], mesh)
    weights, used = sharding.replicate((np.asarray(weights, np.float32), np.asarray(self.capacities, np.int32)),
                                       mesh)
    largest = max(self.capacities)
    return fitting.fit_seeds(self.models, lambda model, buckets, weight, used_capacity: level_loss(
        model, buckets, largest, weight, used_capacity), schedule, hooks, resume, args=(buckets, weights, used),
        mesh=mesh, batch_seeds=[c.network_seed for c in self.configs])


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
  checkpoint, the file its separate run would leave (its decoded views, for `experiments.segment_errors`).
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
      saved = read_training(self.path)
      return None if saved is None else [saved]
    saved = read_training_seeds(self.path)
    if saved is not None and len(saved) != num_seeds:
      raise CheckpointError(f"{self.path} holds {len(saved)} seeds; this run has {num_seeds}")
    return saved

  def write(self, states: list[tuple], finished: bool) -> None:
    """states: each seed's (hierarchy, meta, progress, decoded), as write_training takes them."""
    if self.path:
      if self.batched:
        write_training_seeds(self.path, states)
      else:
        write_training(self.path, *states[0])
    if finished and self.seed_paths:
      for path, state in zip(self.seed_paths, states):
        write_training(path, *state)


def _train_levels(spec: HierarchySpec, demos: list[Demonstration], configs: list[TrainConfig],
                  validate: list[Callable[[PHPHierarchy], float]] | None, log: Callable[[int, dict], None],
                  store: _Store) -> list[tuple[PHPHierarchy, dict]]:
  """The level-wise loop of train_hierarchy (one seed, not batched) and train_seeds."""
  configs = with_common_buckets([prepare(spec, d, in_mode(c, "levelwise")) for d, c in zip(demos, configs)])
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
    decoded[s] = decoded_views(state)

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
      resume = [restore_progress(store.path, state, model)
                for state, model in zip(saved, models)] if in_progress else None
      if resume is None:
        for s, (view, capacity) in enumerate(zip(level_views, fit.capacities)):
          padding = views.padding_fraction(views.length_buckets(view, configs[s].length_buckets))
          logs[s]({"level": level, "capacity": capacity, "view_length": int(view.length.max()),
                   "padding": round(padding, 4)})
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
