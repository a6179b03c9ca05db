r"""Where a trained run's decoded hierarchy differs from the supervisor's, on its weak demonstrations.

  python -m experiments.segmentation --run=runs/nc_sweep/num_demos=64,num_strong=8,seed=1 --level=1

Rebuilds the run's training demonstrations from its results.json, reads the views decoded during training
from its checkpoint, and prints per level: how many weak demonstrations the decoding got wrong, each wrong
one classified as a split (a call of the supervisor's decoded as several, the same procedure pushed again),
a merge (several calls decoded as one) or other (a procedure mistaken, or both), the procedures where
splits and merges start, and the first --show of them side by side.
"""
from __future__ import annotations

import collections
import json
import os

import numpy as np
from absl import app, flags

from php_jax import agreement, checkpoint, datasets, tasks, views

_RUN = flags.DEFINE_string("run", None, "A training run's workdir (results.json, checkpoint.msgpack).")
_LEVEL = flags.DEFINE_integer("level", None, "Level to report (default: every level below the root).")
_SHOW = flags.DEFINE_integer("show", 3, "Wrong demonstrations printed side by side, per level.")


def classify(truth_procs, truth_taus, procs, taus) -> tuple[str, list[int]]:
  """One demonstration at one level: truth_* and decoded [n] frames per operation → (kind, the operations
  where a call starts in one but not the other). kind: correct, split, merge or other."""
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
  splits and merges happen, and the wrong ones' frames (truth, decoded) as "name:τ" lists."""
  true_procs, true_taus = np.asarray(demos.procedures), np.asarray(demos.counters)
  kinds, where, wrong = collections.Counter(), collections.Counter(), []

  def frames(procedures, counters):
    return [f"{names[i]}:{j}" for i, j in zip(procedures, counters)]

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


def main(argv):
  del argv
  paths = [os.path.join(_RUN.value, name) for name in ("results.json", "checkpoint.msgpack")]
  for path in paths:
    if not os.path.isfile(path):
      raise app.UsageError(f"{path} does not exist: --run must be a finished training run's workdir")
  with open(paths[0]) as f:
    results = json.load(f)
  if results.get("model", "php") != "php":
    raise app.UsageError(f"{_RUN.value} holds a {results['model']} run, which has no hierarchy to decode")
  task = tasks.get(results["task"])
  demos = datasets.training_demos(task, results["seed"], results["num_demos"], results["num_strong"])
  spec = task.spec
  decoded = checkpoint.read_decoded(paths[1])
  view = views.lowest_view(demos, spec.num_levels)
  for level in range(spec.num_levels - 1, 0, -1):
    if _LEVEL.value in (None, level):
      report = level_report(demos, view, level, *decoded[level], spec.levels[level])
      print(json.dumps({"level": level, "kinds": report["kinds"], "where": report["where"]}))
      for row in report["wrong"][:_SHOW.value]:
        print(f"  demo {row['demo']} ({row['kind']})\n    supervisor {' '.join(row['truth'])}\n"
              f"    decoded    {' '.join(row['decoded'])}")
    view = views.view_above(demos, view, level, *decoded[level])


if __name__ == "__main__":
  flags.mark_flags_as_required(["run"])
  app.run(main)
