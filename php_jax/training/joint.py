"""Joint Expectation–Gradient training: every level at once, with the hierarchy's own root (no stand-in).

The loss is `objective.stack_loss`, the weighted negative log-likelihood of the demonstrations' elementary
actions under the whole hierarchy; its gradient is the EG gradient of every level's networks at once.
Demonstrations are batched by length into buckets.
"""
from __future__ import annotations

import time
from typing import Callable

import numpy as np
from flax import nnx

from php_jax import fitting, sharding
from php_jax.data import views
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import call_graph, segmentation, split_search
from php_jax.training.config import ConfigError, TrainConfig, in_mode, prepare
from php_jax.training.networks import make_hierarchy
from php_jax.training.objective import (annealed_temperature, counter_capacity, demonstration_log_likelihoods,
                                        stack_loss)
from php_jax.training.resume import CountedLog, read_training, restore_progress, resume_from, run_settings, write_training


def joint_capacity(demos: Demonstration, spec: HierarchySpec, config: TrainConfig,
                   hinted: tuple[Demonstration, ...] = ()) -> tuple[int, ...]:
  """Counter capacity per level, root first (`objective.counter_capacity` of the strong demonstrations'
  counters at that level; config.capacity when nothing is annotated, at least config.min_capacity). The
  root's longest annotated call is scaled by how much longer the longest demonstration is than the longest
  annotated one: weak demonstrations may need more root operations. hinted: demonstrations with the
  segmentation's partial annotation (`segmentation.hinted_demonstrations`: of demos, and of any others the run
  reads); below the root, their segmented calls count as annotated ones, so a level the segmentation annotates
  has no more counters than its calls need."""
  taus, strong, lengths = np.asarray(demos.counters), np.asarray(demos.strong), np.asarray(demos.length)
  least = config.min_capacity or (0,) * spec.num_levels

  def annotated(level: int) -> np.ndarray:
    segmented = [np.asarray(h.counters)[..., level].ravel() for h in hinted] if level else []
    return np.concatenate([taus[strong][..., level].ravel(), *segmented])

  return tuple(counter_capacity(annotated(level), config.capacity, least[level],
                                *((lengths.max(), lengths[strong].max()) if level == 0 and strong.any() else ()))
               for level in range(spec.num_levels))


def unexplained(hierarchy: PHPHierarchy, capacity: tuple[int, ...], demos: Demonstration) -> int:
  """How many of demos no call stack within capacity and the hierarchy's call graph explains, whatever its
  weights: training leaves them out (their log-likelihood is −inf, the loss infinite), and the model cannot act
  as they do."""
  return int(np.sum(~np.isfinite(demonstration_log_likelihoods(hierarchy, capacity, demos))))


def train_joint(spec: HierarchySpec, demos: Demonstration, config: TrainConfig,
                validate: Callable[[PHPHierarchy], float] | None = None, log: Callable[[dict], None] = print,
                checkpoint_path: str | None = None,
                validation_demos: Demonstration | None = None) -> tuple[PHPHierarchy, dict]:
  """Trains every level together (config.training unset or "joint", else ValueError) for config.iterations
  Adam iterations, keeping the snapshot with the best validate(hierarchy) (config.snapshot's rule); the
  first config.segment_iterations of them on the segmentation's partial annotation (`segmentation`;
  ConfigError if config.segment_rule does not apply to the actions). Then config.split_rounds rounds of the
  split search (`split_search`), judged on validation_demos (default: demos), each logged as
  {"split_search": entry}. Checkpoints and resumes as levelwise.train_hierarchy does (the same log protocol); a
  checkpoint made with other settings raises CheckpointError. Returns the hierarchy and a report {capacity,
  unexplained (`unexplained`, also in the first row logged), losses, best_iteration, validation, seconds, and
  split_search: the rounds' entries where there were any}; after a split search, validation is the final
  hierarchy's score and best_iteration the snapshot the search started from."""
  config = prepare(spec, demos, in_mode(config, "joint"))
  graph = call_graph.resolve(config.call_graph, demos, spec)
  for name in ("segment_iterations", "split_rounds"):
    if getattr(config, name) and call_graph.restricts(graph):
      raise ConfigError(name, "needs every procedure free to take any operation; this run's call graph "
                        f"restricts some (the hierarchy's, or --call_graph={config.call_graph}'s)")
  hierarchy = make_hierarchy(spec, config, graph)
  settings = run_settings(spec, demos, config)
  capacity = joint_capacity(demos, spec, config)
  hinted = None
  if config.segment_iterations:
    rule = segmentation.read_rule(demos, config.segment_rule)
    if rule is None:
      raise ConfigError("segment_iterations", f"the demonstrations' actions show nothing that --segment_rule="
                        f"{config.segment_rule} segments ({segmentation.UNSEGMENTED[config.segment_rule]}); use 0")
    hinted = segmentation.hinted_demonstrations(demos, capacity, rule)
    # The judge's calls must fit too, or it cannot tell the split search's candidates apart.
    judged = () if validation_demos is None else (
        segmentation.hinted_demonstrations(validation_demos, capacity, rule),)
    capacity = joint_capacity(demos, spec, config, (hinted, *judged))
  saved = read_training(checkpoint_path)
  counted_log, resume, report = CountedLog(log), None, None
  if saved is not None:
    counted_log.resumed(resume_from(checkpoint_path, saved, settings, hierarchy))
    resume = restore_progress(checkpoint_path, saved, hierarchy) if saved[0]["progress"] else None
    report = saved[0]["report"] or None
  left_out = unexplained(hierarchy, capacity, demos) if report is None else None
  if resume is None and report is None:
    padding = views.padding_fraction(views.length_buckets(demos, config.length_buckets))
    counted_log({"training": "joint", "capacity": list(capacity), "padding": round(padding, 4),
                 "unexplained": left_out})

  def save(progress: fitting.Progress | None, report: dict | None = None) -> None:
    if checkpoint_path:
      write_training(checkpoint_path, hierarchy, {"level": "joint", "report": report or {},
                                                             "settings": settings, "logged": counted_log.logged},
                                progress, {})

  if report is None:
    start = time.time()
    progress = _fit(hierarchy, demos, hinted, capacity, config, resume,
                    fitting.Hooks((lambda it, loss: validate(hierarchy)) if validate else None, counted_log,
                                  save if checkpoint_path else None))
    report = {"capacity": list(capacity), "unexplained": left_out, "losses": progress.losses,
              "best_iteration": progress.best_iteration,
              "validation": progress.best_score, "seconds": time.time() - start}
    if config.split_rounds:
      report["split_search"] = []
      save(None, report)
  if config.split_rounds:
    start, seconds_before = time.time(), report["seconds"]

    def on_round(kept: PHPHierarchy, rounds: list[dict]) -> None:
      nnx.update(hierarchy, nnx.state(kept, nnx.Param))
      counted_log({"split_search": rounds[-1]})
      report.update(split_search=rounds, seconds=seconds_before + time.time() - start)
      save(None, report)

    if not report["split_search"]:
      counted_log({"split_rounds": config.split_rounds})
    judge = demos if validation_demos is None else validation_demos
    split_search.search(hierarchy, capacity, demos, judge, config, report["split_search"], on_round)
    if validate:  # every round trains what it keeps, "unchanged" too; best_iteration: where the search started
      report["validation"] = validate(hierarchy)
  return hierarchy, report


def _fit(hierarchy: PHPHierarchy, demos: Demonstration, hinted: Demonstration | None, capacity: tuple[int, ...],
         config: TrainConfig, resume: fitting.Progress | None, hooks: fitting.Hooks) -> fitting.Progress:
  """config.iterations of full-batch Adam on the stack loss (annealed where config.anneal_temperature ≠ 1),
  the first config.segment_iterations on hinted, the rest on demos; from resume where given."""
  mesh = sharding.data_mesh()  # with more than one device, each bucket is split over all of them
  if config.anneal_temperature != 1:  # the loss logged while T > 1 is the tempered one
    def tempered(h, iteration, buckets):
      temperature = annealed_temperature(config.anneal_temperature, iteration, config.iterations)
      return stack_loss(h, buckets, capacity, config.strong_weight, temperature, config.call_penalty)

    loss = fitting.IterationLoss(tempered)
  else:
    def loss(h, buckets):
      return stack_loss(h, buckets, capacity, config.strong_weight, call_penalty=config.call_penalty)

  def fit(data: Demonstration, iterations: int, resume: fitting.Progress | None) -> fitting.Progress:
    return fitting.fit(hierarchy, loss, config.schedule(iterations), hooks, resume,
                       args=(views.training_buckets(data, config.length_buckets, mesh),), mesh=mesh)

  if hinted is not None and (resume is None or resume.iteration < config.segment_iterations):
    resume = fit(hinted, config.segment_iterations, resume)
    nnx.update(hierarchy, resume.params)  # fit left the best-validated snapshot; training goes on from the last
  return fit(demos, config.iterations, resume)
