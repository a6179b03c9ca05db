r"""Where a trained run's decoded hierarchy differs from the supervisor's, on its weak demonstrations.

  python -m experiments.segment_errors --run=runs/nc_sweep/num_demos=64,num_strong=8,seed=1 --level=1

Rebuilds the run's training demonstrations from its results.json and takes each level's segmentation of
them: for a level-wise run the views decoded during training (in its checkpoint), for a joint run
(--training=joint) the trained hierarchy's most likely call stack (whole-stack Viterbi). Prints per level:
how many weak demonstrations the segmentation got wrong, each wrong one classified as a split (a call of the
supervisor's decoded as several, the same procedure pushed again), a merge (several calls decoded as one) or
other (a procedure mistaken, or both), the procedures where splits and merges start, and the first --show of
them side by side.
"""
from __future__ import annotations

import collections
import json
import os

import numpy as np
from absl import app, flags

from experiments.common import cli
from php_jax.analysis import decoding
from php_jax.data import agreement, views
from php_jax.envs import datasets, tasks
from php_jax.training import checkpoint, resume

_RUN = flags.DEFINE_string("run", None, "A training run's workdir (results.json, checkpoint/).")
_LEVEL = flags.DEFINE_integer("level", None, "Level to report (default: every level below the root).")
_SHOW = flags.DEFINE_integer("show", 3, "Wrong demonstrations printed side by side, per level.", lower_bound=0)


def classify(truth_procs, truth_taus, procs, taus) -> tuple[str, list[int]]:
  """One demonstration at one level: truth_* and decoded [n] frames per operation → (kind, the operations
  where a call starts in one but not the other). kind: correct, split, merge or other (also where nothing was
  decoded: no path of the levels below explains the demonstration)."""
  if not len(procs):
    return "other", []
  if np.array_equal(truth_procs, procs) and np.array_equal(truth_taus, taus):
    return "correct", []
  truth_starts, starts = set(np.flatnonzero(truth_taus == 0)), set(np.flatnonzero(taus == 0))
  extra, missing = sorted(starts - truth_starts), sorted(truth_starts - starts)
  if np.array_equal(truth_procs, procs) and extra and not missing:
    return "split", extra
  if np.array_equal(truth_procs, procs) and missing and not extra:
    return "merge", missing
  return "other", extra + missing


def level_report(demos, view: views.LevelView, level: int, procs, taus, names) -> dict:
  """Counts of each kind over weak demonstrations that carry the supervisor's stack, the procedures where
  splits and merges happen, and the wrong ones' frames (truth, decoded) as "name:τ" lists ("?:-1" where no
  path explains the demonstration)."""
  true_procs, true_taus = np.asarray(demos.procedures), np.asarray(demos.counters)
  kinds, where, wrong = collections.Counter(), collections.Counter(), []

  def frames(procedures, counters):
    return [f"{names[i] if i >= 0 else '?'}:{j}" for i, j in zip(procedures, counters)]

  for b in agreement.weak_with_stack(demos, view, level):
    n, times = view.length[b], view.times[b, :view.length[b]]
    truth = true_procs[b, times, level], true_taus[b, times, level]
    kind, steps = classify(*truth, procs[b, :n], taus[b, :n])
    kinds[kind] += 1
    where.update(f"{kind} in {names[truth[0][k]]}" for k in steps if kind in ("split", "merge"))
    if kind != "correct":
      wrong.append({"demo": b, "kind": kind, "truth": frames(*truth),
                    "decoded": frames(procs[b, :n], taus[b, :n])})
  return {"kinds": dict(kinds), "where": dict(where), "wrong": wrong}


def _read_results(path: str) -> dict:
  """A finished PHP run's results.json; raises ValueError naming the file if it is not one."""
  try:
    with open(path, encoding="utf-8") as f:
      results = json.load(f)
  except (OSError, ValueError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
    raise ValueError(f"{path}: not a training run's results ({e})") from None
  if not isinstance(results, dict):
    raise ValueError(f"{path}: not a training run's results (not a JSON object)")
  if results.get("model", "php") != "php":
    raise ValueError(f"{path} is a {results['model']} run, which has no hierarchy to decode")
  if "hierarchy" in results and "seed" not in results:  # experiments.fit's
    raise ValueError(f"{path} is a fit run, whose actions-only demonstrations carry no stack to compare with: "
                     "experiments.decode on a file of annotated ones prints the agreement per level, and "
                     "experiments.show draws one")
  for key, kind in (("task", str), ("seed", int), ("num_demos", int), ("num_strong", int)):
    if not isinstance(results.get(key), kind):
      raise ValueError(f"{path}: not a training run's results (needs {kind.__name__} {key!r})")
  return results


def report(run: str, level: int | None, show: int) -> None:
  """Prints the report of the run's workdir for one level (None: every level below the root). Raises
  ValueError naming the file or flag at fault before printing anything."""
  paths = [os.path.join(run, name) for name in ("results.json", checkpoint.TRAINING_DIR)]
  for path in paths:
    if not os.path.exists(path):
      raise ValueError(f"{path} does not exist: --run must be a finished training run's workdir")
  results = _read_results(paths[0])
  try:
    task = tasks.get(results["task"])
  except ValueError as e:
    raise ValueError(f"{paths[0]}: {e}") from None
  spec = task.spec
  if level is not None and not 1 <= level < spec.num_levels:
    raise ValueError(f"--level must be in 1..{spec.num_levels - 1} for {task.name}; got {level}")
  demos = datasets.training_demos(task, results["seed"], results["num_demos"], results["num_strong"])
  frames = _segmentation(run, results, paths[1], demos, spec.num_levels)
  view = views.lowest_view(demos, spec.num_levels)
  for k in range(spec.num_levels - 1, 0, -1):
    decoded = frames(view, k)
    if level in (None, k):
      found = level_report(demos, view, k, *decoded, spec.levels[k])
      print(json.dumps({"level": k, "kinds": found["kinds"], "where": found["where"]}))
      for row in found["wrong"][:show]:
        print(f"  demo {row['demo']} ({row['kind']})\n    supervisor {' '.join(row['truth'])}\n"
              f"    decoded    {' '.join(row['decoded'])}")
    view = views.view_above(demos, view, k, *decoded)


def _segmentation(run: str, results: dict, checkpoint_path: str, demos, num_levels: int):
  """(level's view, level) → the run's (procedures, τ) [B, T] at each of the view's operations. Raises
  ValueError naming the file when the run holds no segmentation of every level below the root."""
  config = results.get("config")
  if isinstance(config, dict) and config.get("training") == "joint":
    _, hierarchy = checkpoint.load_policy(run)
    capacity = checkpoint.saved_capacity(run)
    if capacity is None:
      raise ValueError(f"{run}: the saved model records no counter capacities (saved by an older version)")
    stack = decoding.decode(hierarchy, capacity, demos)

    def at_view(view: views.LevelView, level: int):
      steps = np.arange(len(view.times))[:, None], np.maximum(view.times, 0), level
      return stack.procedures[steps], stack.counters[steps]
    return at_view
  decoded = resume.read_decoded(checkpoint_path)
  missing = [k for k in range(1, num_levels) if k not in decoded]
  if missing:
    raise ValueError(f"{checkpoint_path}: no decoded views of level {missing[0]} (training did not finish?)")
  return lambda view, level: decoded[level]


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  try:
    report(_RUN.value, _LEVEL.value, _SHOW.value)
  except ValueError as e:  # CheckpointError is one
    cli.fail(str(e))


if __name__ == "__main__":
  flags.mark_flags_as_required(["run"])
  app.run(main, flags_parser=cli.parse_flags)
