"""A recipe's candidates trained, each as its own run in workdir/candidates/NAME, and the one most likely on the
held-out demonstrations kept: its model, metrics and training summary become the run's, tested as a single
run's would be, and results.json's "recipe" says what was tried and how each candidate scored.

A candidate's score is judged on the demonstrations by their actions alone: first how many of the held-out
(validation) and training demonstrations some call stack within its counter capacities and call graph
explains (log P > −inf: a candidate whose call graph, read off a few annotated demonstrations, forbids what
others do cannot act as they do), then Σ log P(actions | observations) / Σ steps over the held-out ones
explained. Each candidate's run resumes and finishes as any run does, so a rerun after an interruption trains
only what was left.
"""
from __future__ import annotations

import dataclasses
import json
import os
import time
from typing import Callable

import numpy as np

from php_jax.data import files
from php_jax.demos import Demonstration
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint, objective, provenance, resume, storage
from php_jax.training.config import TrainConfig, resolved
from php_jax.training.recipe import Recipe
from php_jax.training.run import (METRICS_FILE, RESULTS_FILE, RUN_FILES, Experiment, WorkdirError, clear_workdir,
                                  made_otherwise, other_settings, print_row, read_finished, train_and_evaluate,
                                  workdir_lock)

CANDIDATES_DIR = "candidates"
SCORE = "held_out_log_likelihood_per_step"
EXPLAINED = "held_out_explained"
TRAINING_EXPLAINED = "training_explained"


def held_out_score(hierarchy: PHPHierarchy, capacity: tuple[int, ...], demos: Demonstration,
                   training: Demonstration | None = None) -> dict:
  """{EXPLAINED: how many of demos some stack within capacity explains, SCORE: Σ log P(actions | observations)
  / Σ steps over those (None if none)}, the annotation unused; with training demonstrations, also
  {TRAINING_EXPLAINED: how many of them some stack explains}."""
  log_p = objective.demonstration_log_likelihoods(hierarchy, capacity, demos)
  explained = np.isfinite(log_p)
  steps = float(np.sum(np.asarray(demos.length)[explained]))
  score = {EXPLAINED: int(explained.sum()), SCORE: float(np.sum(log_p[explained]) / steps) if steps else None}
  if training is not None:
    score[TRAINING_EXPLAINED] = int(np.isfinite(objective.demonstration_log_likelihoods(
        hierarchy, capacity, training)).sum())
  return score


def rank(score: dict, training: bool = True) -> tuple:
  """A candidate's test results as a sort key: more demonstrations explained, held out and (with training)
  training ones together, then likelier on the held-out ones."""
  explained = score[EXPLAINED] + (score.get(TRAINING_EXPLAINED, 0) if training else 0)
  return (explained, -np.inf if score[SCORE] is None else score[SCORE])


def train_and_choose(experiment: Experiment, config: TrainConfig, recipe: Recipe, workdir: str,
                     overwrite: bool = False, wait: bool = False, echo: Callable[[dict], None] = print_row) -> dict:
  """Trains config's PHP hierarchy by the recipe in workdir and returns its results.json. One candidate: an
  ordinary run (`run.train_and_evaluate`) with its settings, results.json's "recipe" saying why. Several:
  each trained in workdir/candidates/NAME (its rows echoed with "candidate": NAME) and judged by
  `held_out_score` on experiment.validation_demos (ValueError if None); the best's model and metrics are
  copied to workdir and tested there. overwrite: train every candidate again. A finished run with the same
  recipe is not trained again."""
  plan = recipe.as_json()
  if len(recipe.candidates) == 1:
    [candidate] = recipe.candidates
    experiment = dataclasses.replace(experiment, extra={**experiment.extra,
                                                        "recipe": {**plan, "chosen": candidate.name}})
    return train_and_evaluate(experiment, candidate.config(config), workdir, overwrite, wait=wait, echo=echo)
  judged_on = experiment.validation_demos
  if judged_on is None:
    raise ValueError(f"{len(recipe.candidates)} candidates need held-out demonstrations to be judged on "
                     "(Experiment.validation_demos)")
  commit = provenance.code_version()
  with workdir_lock(workdir, wait):
    clear_workdir(workdir, RUN_FILES + (CANDIDATES_DIR,), overwrite)
    finished = _finished(workdir, experiment, config, recipe)
    if finished:
      echo({"test": finished["test"], "wall_seconds": finished["wall_seconds"], "finished_before": True})
      return finished
    tried = []
    for candidate in recipe.candidates:
      run_dir = os.path.join(workdir, CANDIDATES_DIR, candidate.name)

      def judge(model, run_dir=run_dir):
        return held_out_score(model, checkpoint.saved_capacity(run_dir), judged_on, experiment.demos)

      results = train_and_evaluate(
          dataclasses.replace(experiment, test=judge, extra={**experiment.extra, "candidate": candidate.name}),
          candidate.config(config), run_dir, overwrite, wait=wait,
          echo=lambda row, name=candidate.name: echo({"candidate": name, **row}))
      tried.append((candidate, results))
    start = time.time()
    counted = all(TRAINING_EXPLAINED in r["test"] for _, r in tried)  # not where an earlier php_jax judged some
    chosen, results = max(tried, key=lambda pair: rank(pair[1]["test"], counted))
    echo({"chosen": chosen.name, **results["test"]})
    model = _adopt(os.path.join(workdir, CANDIDATES_DIR, chosen.name), workdir, experiment.name, results)
    echo({"phase": "testing"})
    summary = {k: v for k, v in results.items() if k not in ("test", "wall_seconds", "commit", "versions",
                                                               "candidate")}
    record = {**plan, "chosen": chosen.name, "demonstrations": _digest(experiment),
              "judged_on": len(judged_on.length),
              "scores": [{"name": c.name, **r["test"], "wall_seconds": r["wall_seconds"]} for c, r in tried]}
    test = experiment.test(model)
    spent = sum(r["wall_seconds"] for _, r in tried) + time.time() - start
    final = {**summary, "recipe": record, "test": test, "wall_seconds": round(spent, 1), "commit": commit,
             "versions": provenance.environment_versions()}
    text = json.dumps(final, indent=1)
    files.write_atomically(os.path.join(workdir, RESULTS_FILE), text.encode())
    echo({"test": test, "wall_seconds": final["wall_seconds"]})
    return json.loads(text)  # as a rerun reads it


def _adopt(run_dir: str, workdir: str, task_name: str, results: dict) -> PHPHierarchy:
  """The chosen candidate's model and metrics.jsonl, written again in workdir; returns the model."""
  for name in (checkpoint.ARCHITECTURE_FILE, checkpoint.MODEL_DIR):
    storage.remove_saved(os.path.join(workdir, name))
  _, model = checkpoint.load_policy(run_dir)
  checkpoint.save_hierarchy(workdir, task_name, model, tuple(results["config"]["hidden"]),
                            list(checkpoint.saved_capacity(run_dir)))
  with open(os.path.join(run_dir, METRICS_FILE), "rb") as f:
    files.write_atomically(os.path.join(workdir, METRICS_FILE), f.read())
  return model


def _finished(workdir: str, experiment: Experiment, config: TrainConfig, recipe: Recipe) -> dict | None:
  """The results.json of a choice that finished in workdir with these settings, recipe and experiment; None
  if none finished there, or one chose among other candidates (whose runs are reused where their settings
  are these). Raises WorkdirError if one finished with other settings or data."""
  results = read_finished(workdir)
  if results is None:
    return None
  recipe_entry = results.get("recipe")
  if not isinstance(recipe_entry, dict):
    raise WorkdirError(f"{workdir} holds a finished run that chose no recipe (an older php_jax's); use a fresh "
                       "workdir, or --overwrite to train again")
  plan = recipe.as_json()
  if {k: recipe_entry.get(k) for k in plan} != json.loads(json.dumps(plan)):
    return None  # other candidates (more restarts, say): each candidate's own run checks its settings
  chosen = [c for c in recipe.candidates if c.name == recipe_entry.get("chosen")]
  asked = resolved(chosen[0].config(config), experiment.demos, experiment.spec) if chosen else None
  differ = other_settings(results, {"task": experiment.name, **experiment.extra}, asked)
  if differ:
    raise made_otherwise(workdir, differ)
  if recipe_entry.get("demonstrations") != _digest(experiment):
    raise WorkdirError(f"{workdir} holds a finished run made with other demonstrations; use a fresh workdir, or "
                       "--overwrite to train again")
  return results


def _digest(experiment: Experiment) -> str:
  """A digest of the training demonstrations (`resume.run_settings`')."""
  return resume.run_settings(experiment.spec, experiment.demos, TrainConfig())["demonstrations"]
