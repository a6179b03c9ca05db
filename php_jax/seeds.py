"""Several seeds of level-wise training as one program.

Each seed has its own demonstrations, initialisation, decoding and root snapshot, exactly as a separate
`train.train_hierarchy` run would; per level, their EG updates run as one vmapped program
(`fitting.fit_seeds`). The seeds' views are padded to common shapes (`views.stack_seeds`: padding copies
weigh 0) and their counter capacities to the largest, each seed's own capacity masking the counters above it
(`objective.lattice_inputs`' used_capacity), so every seed's loss and gradients are its separate run's, to
float rounding. Decoding and validation run per seed. Progress is checkpointed in one file for all seeds.
"""
from __future__ import annotations

import dataclasses
import time
from typing import Callable, Sequence

import numpy as np

from php_jax import call_graph, checkpoint, fitting, sharding, train, views
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.objective import level_loss


def train_seeds(spec: HierarchySpec, demos: Sequence[Demonstration], configs: Sequence[train.TrainConfig],
                validate: Sequence[Callable[[PHPHierarchy], float]] | None = None,
                log: Callable[[int, dict], None] = lambda s, row: print(s, row),
                checkpoint_path: str | None = None,
                seed_checkpoint_paths: Sequence[str] | None = None) -> list[tuple[PHPHierarchy, dict]]:
  """train.train_hierarchy for each seed s (demos[s], configs[s], validate[s]), all at once. The configs may
  differ only in their seed and strong weight (the balanced default follows each seed's demonstrations), and
  the seeds need as many length buckets and the same strong warm-up at every level (else ValueError), as the
  training sets of `experiments.train` have (the same numbers of demonstrations and of annotated ones).
  log(s, row) gets seed s's rows, as train_hierarchy's log would (a resumed run first gets {"resumed": True,
  ..., "logged": n} for each seed). With checkpoint_path, progress is saved there (every seed in one file) and
  a rerun resumes it. When training ends, seed_checkpoint_paths[s] gets seed s's finished training
  checkpoint, the file its separate run would leave (its decoded views, for `experiments.segmentation`).
  Returns each seed's (hierarchy, report)."""
  configs = [train.prepare(spec, d, c) for d, c in zip(demos, configs)]
  others = {dataclasses.replace(c, seed=0, strong_weight=None) for c in configs}
  if len(others) != 1:
    raise ValueError("seeds trained together must have the same settings but for their seed")
  if configs[0].training != "levelwise":
    raise ValueError("seeds are trained together level-wise only (training: levelwise)")
  graph = common_call_graph(spec, demos, configs)
  num_seeds = len(configs)
  hierarchies = [train.make_hierarchy(spec, c, graph) for c in configs]
  settings = [train.run_settings(spec, d, c) for d, c in zip(demos, configs)]
  reports, decoded = [{} for _ in configs], [{} for _ in configs]
  seed_logs = [train.CountedLog(lambda row, s=s: log(s, row)) for s in range(num_seeds)]
  saved = checkpoint.read_training_seeds(checkpoint_path)
  if saved is not None:
    if len(saved) != num_seeds:
      raise checkpoint.CheckpointError(f"{checkpoint_path} holds {len(saved)} seeds; this run has {num_seeds}")
    for s, (meta, _) in enumerate(saved):
      seed_logs[s].resumed(train.resume_from(checkpoint_path, saved[s], settings[s], hierarchies[s]))
      reports[s] = {int(k): v for k, v in meta["report"].items()}
      decoded[s] = checkpoint.decoded_views(saved[s])

  def counted_log(s: int, row: dict) -> None:
    seed_logs[s](row)

  def save(level: int, progress: list[fitting.Progress] | None) -> None:
    states = [(hierarchies[s], {"level": level, "report": reports[s], "settings": settings[s],
                                "logged": seed_logs[s].logged}, progress and progress[s], decoded[s])
              for s in range(num_seeds)]
    if checkpoint_path:
      checkpoint.write_training_seeds(checkpoint_path, states)
    if level == -1 and seed_checkpoint_paths:
      for path, state in zip(seed_checkpoint_paths, states):
        checkpoint.write_training(path, *state)

  level_views = [views.lowest_view(d, spec.num_levels) for d in demos]
  for level in range(spec.num_levels - 1, -1, -1):
    if level not in reports[0]:
      in_progress = saved is not None and saved[0][0]["progress"] is not None and saved[0][0]["level"] == level
      entries = _train_level(spec, demos, level_views, level, hierarchies, configs, validate, counted_log,
                             decoded, lambda progress, level=level: save(level, progress),
                             saved if in_progress else None, checkpoint_path)
      for report, entry in zip(reports, entries):
        report[level] = entry
      save(level - 1, None)  # the level is complete: its result survives a restart
    elif level == 0:  # finished before: the seeds' own checkpoints may not all have been written
      save(-1, None)
    if level > 0:
      level_views = [views.view_above(d, v, level, *decoded[s][level])
                     for s, (d, v) in enumerate(zip(demos, level_views))]
  return list(zip(hierarchies, reports))


def common_call_graph(spec: HierarchySpec, demos: Sequence[Demonstration],
                      configs: Sequence[train.TrainConfig]) -> tuple:
  """The call graph every seed's config and demonstrations give (`call_graph.resolve`); ValueError if they
  differ (seeds trained together share one program, so one graph)."""
  graphs = {call_graph.resolve(c.call_graph, d, spec) for d, c in zip(demos, configs)}
  if len(graphs) != 1:
    raise ValueError(f"the seeds' annotated demonstrations show different call graphs ({configs[0].call_graph}); "
                     "train them separately, or allow every operation (call_graph=all)")
  return graphs.pop()


def _train_level(spec, demos, level_views, level, hierarchies, configs, validate, log, decoded, save, saved,
                 checkpoint_path) -> list[dict]:
  """Fits one level of every seed (resuming `saved` if given) and decodes each seed's weak views into
  decoded[s][level]; each seed's report entry."""
  start, is_root = time.time(), level == 0
  capacities = [train.level_capacity(v, level, c) for v, c in zip(level_views, configs)]
  models = [train.level_model(spec, h, level, c) for h, c in zip(hierarchies, configs)]
  resume = ([checkpoint.restore_progress(checkpoint_path, state, model) for state, model in zip(saved, models)]
            if saved is not None else None)
  if resume is None:
    for s, (view, capacity) in enumerate(zip(level_views, capacities)):
      log(s, {"level": level, "capacity": capacity, "view_length": int(view.length.max())})
  warmups = {train.warmup_iterations(v, c, is_root) for v, c in zip(level_views, configs)}
  if len(warmups) != 1:
    raise ValueError(f"level {level}: the seeds' strong warm-ups differ ({sorted(warmups)}): some have no strong "
                     "or no weak views there")
  warmup = warmups.pop()
  config, mesh = configs[0], sharding.data_mesh()
  weights, used = sharding.replicate((np.asarray([train.level_strong_weight(c, is_root) for c in configs],
                                                 np.float32), np.asarray(capacities, np.int32)), mesh)

  def loss(model, buckets, weight, used_capacity):
    return level_loss(model, buckets, max(capacities), weight, used_capacity)

  def on_eval(iteration, losses):
    if not (is_root and validate):
      return [None] * len(models)
    return [v(h) for v, h in zip(validate, hierarchies)]

  def fit(parts, iterations, progress):
    buckets = views.stack_seeds([views.length_buckets(p, config.length_buckets) for p in parts], mesh)
    return fitting.fit_seeds(models, loss, iterations, config.learning_rate, config.eval_every, on_eval,
                             lambda s, row: log(s, {"level": level, **row}), progress,
                             save if checkpoint_path else None, config.snapshot,
                             args=(buckets, weights, used), mesh=mesh)

  if warmup and (resume is None or resume[0].iteration < warmup):
    resume = fit([views.select(v, v.strong) for v in level_views], warmup, resume)
  progress = fit(level_views, warmup + config.iterations, resume)
  return [train.finish_level(d, v, level, m, capacity, c, p, decoded[s], start)
          for s, (d, v, m, capacity, c, p) in enumerate(zip(demos, level_views, models, capacities, configs,
                                                             progress))]
