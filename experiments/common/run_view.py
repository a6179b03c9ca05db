"""What `experiments.show` and a run's report read from a workdir (the trained hierarchy with its counter
capacities, the names of its procedures and elementary actions, its settings, the demonstrations it was
trained on: a task's rebuilt from the run's seed, a fit's read from its file), and what they show of one
demonstration: its decoded call stack and posterior, beside its own stack where it has one."""
from __future__ import annotations

import dataclasses
import json
import os
from typing import Callable

import numpy as np

from experiments.common import pictures
from php_jax.analysis import decoding
from php_jax.data import agreement, call_tree, demo_files, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import datasets, tasks
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint
from php_jax.training.run import RESULTS_FILE


@dataclasses.dataclass(frozen=True)
class RunView:
  """A trained hierarchy's run.

  Attributes:
    workdir: the run's directory.
    hierarchy: the trained model; capacity: its counter capacity per level, root first.
    results: results.json's contents ({} for a model saved without one).
    action_name: an elementary action (a list of ints) → its text.
  """
  workdir: str
  hierarchy: PHPHierarchy
  capacity: tuple[int, ...]
  results: dict
  action_name: Callable[[list[int]], str]

  def procedure_name(self, level: int, procedure: int) -> str:
    """The name of a level's procedure ("?" for an unknown one, −1)."""
    names = self.hierarchy.spec.levels[level]
    return names[procedure] if 0 <= procedure < len(names) else "?"


def load(workdir: str) -> RunView:
  """The run in workdir. Raises ValueError naming the file at fault, or saying why the model has no call
  stack to show (a flat LSTM)."""
  if not workdir:
    raise ValueError("--policy: must name a run's workdir; got ''")
  try:
    _, model = checkpoint.load_policy(workdir)
  except FileNotFoundError as e:
    raise ValueError(str(e)) from None
  capacity = checkpoint.saved_capacity(workdir)
  if not isinstance(model, PHPHierarchy):
    raise ValueError(f"{workdir} holds a flat baseline, which has no call stack to show")
  if capacity is None:
    raise ValueError(f"{workdir}: the saved model records no counter capacities (saved by an older version)")
  results = read_results(workdir)
  return RunView(workdir, model, tuple(capacity), results, _action_namer(model.spec.name, results))


def read_results(workdir: str) -> dict:
  """workdir's results.json ({} if it has none); ValueError naming the file if it is not a JSON object."""
  path = os.path.join(workdir, RESULTS_FILE)
  if not os.path.exists(path):
    return {}
  try:
    with open(path, encoding="utf-8") as f:
      results = json.load(f)
  except (OSError, ValueError) as e:
    raise ValueError(f"{path}: cannot read the run's results ({e})") from None
  if not isinstance(results, dict):
    raise ValueError(f"{path}: not a run's results (not a JSON object)")
  return results


def _action_namer(task_name: str, results: dict) -> Callable[[list[int]], str]:
  """A fit's hierarchy file's "action_names", else the registered task's action names, else indices."""
  hierarchy_file = results.get("hierarchy")
  if isinstance(hierarchy_file, str) and os.path.isfile(hierarchy_file):
    try:
      names = demo_files.read_hierarchy(hierarchy_file).action_names
    except demo_files.DemoFileError:
      names = None
    if names:
      return demo_files.action_namer(names)
  try:
    return tasks.get(task_name).action_name
  except ValueError:  # not a task php_jax knows (a fit's hierarchy without "action_names")
    return demo_files.action_namer(None)


def decoded(run: RunView, batch: Demonstration, indices: list[int]) -> list[tuple[dict, list[str]]]:
  """What is shown of each demonstration of batch [B, ...] at indices (decoded as one program): ({"decoded",
  "supervisor" (None where it has no stack): call_tree.Call; "marginals": per level [T, K_i]; "actions": their
  names; "log_likelihood" (None where no stack fits); "agreement": per level below the root, the fraction of
  annotated steps whose decoded frame is the demonstration's}, the text lines)."""
  chosen = views.select(batch, indices)
  stacks, marginals = decoding.explain(run.hierarchy, run.capacity, chosen)
  shown = []
  for b in range(len(indices)):
    length = int(chosen.length[b])
    actions = [run.action_name([int(a) for a in action]) for action in chosen.actions[b, :length]]
    tree = call_tree.calls(stacks.procedures[b], stacks.counters[b], length)
    procs, taus = chosen.procedures[b, :length], chosen.counters[b, :length]
    supervisor = call_tree.calls(procs, taus) if (procs != UNKNOWN).any() else None
    log_likelihood = float(stacks.log_likelihood[b])
    finite = np.isfinite(log_likelihood)
    lines = [f"decoded call stack ({f'log-likelihood {log_likelihood:.3f}' if finite else 'no stack fits it'}):",
             *("  " + line for line in call_tree.text(tree, run.procedure_name, actions))]
    agreed = {}
    if supervisor:
      lines += ["the demonstration's own call stack:",
                *("  " + line for line in call_tree.text(supervisor, run.procedure_name, actions))]
      for level in range(1, procs.shape[1]) if finite else ():  # no decoded stack where none fits
        measured = agreement.stack_agreement(procs, taus, stacks.procedures[b, :length],
                                             stacks.counters[b, :length], level)
        if measured:
          agreed[level] = measured[0]  # exact: the procedure ids of the demonstration's own stack
          lines.append(f"level {level}: frames (procedure, counter) agree on {agreed[level]:.3f} of the annotated "
                       "steps" + _boundaries(procs, taus, stacks, b, level))
    shown.append(({"decoded": tree, "supervisor": supervisor, "marginals": [m[b] for m in marginals],
                   "actions": actions, "log_likelihood": log_likelihood if finite else None,
                   "agreement": agreed}, lines))
  return shown


def _boundaries(procs, taus, stacks, b: int, level: int) -> str:
  """"; call boundaries: H of N found, P decoded (F1 ...)" for a stack known down to level: where the calls
  at level start, which frames alone do not show (a level above resuming splits a call)."""
  length = len(procs)
  scores = agreement.stack_boundary_scores(procs[None], taus[None], stacks.procedures[b:b + 1, :length],
                                           stacks.counters[b:b + 1, :length], [length], level)
  if scores is None:
    return ""
  return (f"; call boundaries: {scores['hits']} of {scores['true']} found, {scores['predicted']} decoded "
          f"(F1 {scores['f1']:.3f})")


def figure(run: RunView, drawn: dict, title: str):
  """The picture of `decoded`'s result."""
  return pictures.stack_figure(title, drawn["decoded"], run.procedure_name, drawn["actions"],
                               drawn["supervisor"], drawn["marginals"])


def demonstrations(run: RunView, path: str | None) -> tuple[Demonstration, str]:
  """(the demonstrations [B, ...], where they come from): the file at path (any demonstration file of the
  hierarchy's size, recorded episodes included), else the run's own training demonstrations. Raises
  ValueError naming the file, or saying why the run has none to rebuild."""
  spec = run.hierarchy.spec
  if path is None:
    path = run.results.get("demos")
    if path is None:
      return _task_demos(run), "its training demonstrations"
    if not isinstance(path, str):
      raise ValueError(f"{run.workdir}/{RESULTS_FILE}: \"demos\" is not a file name; give --demos")
  batch, _ = demo_files.read_demonstrations(path, spec)
  return batch, path


def _task_demos(run: RunView) -> Demonstration:
  results = run.results
  kinds = {"task": str, "seed": int, "num_demos": int, "num_strong": int}
  if not all(isinstance(results.get(k), kind) for k, kind in kinds.items()):
    raise ValueError(f"{run.workdir}: no results.json saying how its demonstrations were made; give --demos")
  try:
    task = tasks.get(results["task"])
  except ValueError as e:
    raise ValueError(f"{run.workdir}/{RESULTS_FILE}: {e}") from None
  mine = run.hierarchy.spec
  if (task.spec.levels, task.spec.action_sizes, task.spec.obs_dim) != (mine.levels, mine.action_sizes, mine.obs_dim):
    raise ValueError(f"{run.workdir}: its model is not a hierarchy of task {task.name!r}, which its results.json "
                     "names; give --demos")
  if not 0 <= results["num_strong"] <= results["num_demos"] or results["num_demos"] < 1:
    raise ValueError(f"{run.workdir}/{RESULTS_FILE}: num_strong {results['num_strong']} of num_demos "
                     f"{results['num_demos']}")
  return datasets.training_demos(task, results["seed"], results["num_demos"], results["num_strong"])
