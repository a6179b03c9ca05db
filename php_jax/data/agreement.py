"""How well decoded weak views (or decoded stacks, or another method's segments) recover the supervisor's
hierarchy: per level, the fraction of elementary steps whose decoded (procedure, counter) equals the
supervisor's, by exact procedure ids and up to a renaming of them (the best one-to-one renaming, by the
Hungarian algorithm); and how well the calls' boundaries are found (precision, recall, F1)."""
from __future__ import annotations

import numpy as np

from php_jax.data import call_tree
from php_jax.data.views import LevelView
from php_jax.demos import UNKNOWN, Demonstration


def weak_with_stack(demos: Demonstration, view: LevelView, level: int) -> list[int]:
  """The weak demonstrations whose supervisor's stack at `level` is known on every elementary step: those
  a decoding can be checked against."""
  true_procs = np.asarray(demos.procedures)[..., level]
  return [int(b) for b in np.flatnonzero(~view.strong) if np.all(true_procs[b, :int(demos.length[b])] != UNKNOWN)]


def agreement_counts(demos: Demonstration, view: LevelView, level: int, procedures, counters):
  """[K, K] counts of weak demonstrations' elementary steps decoded as procedure i at `level` whose
  supervisor's procedure is j, with equal counters (None if no weak demonstration carries the supervisor's
  stack), and the number of such steps."""
  true_procs, true_taus = np.asarray(demos.procedures), np.asarray(demos.counters)
  num_procs = int(max(true_procs[..., level].max(), np.max(procedures))) + 1
  counts, total = np.zeros((num_procs, num_procs), np.int64), 0
  for b in weak_with_stack(demos, view, level):
    bounds = list(view.times[b, :view.length[b]]) + [int(demos.length[b])]
    for k in range(view.length[b]):
      steps = slice(bounds[k], bounds[k + 1])
      same_tau = true_taus[b, steps, level] == counters[b, k]
      np.add.at(counts[procedures[b, k]], true_procs[b, steps, level][same_tau], 1)
      total += bounds[k + 1] - bounds[k]
  return (counts, total) if total else (None, 0)


def exact_fraction(counts, total: int) -> float | None:
  """Agreement by exact ids from agreement_counts' result."""
  return None if counts is None else float(np.trace(counts) / total)


def relabelled_fraction(counts, total: int) -> float | None:
  """Agreement under the best renaming from agreement_counts' result (None, as when no weak demonstration
  carries the stack)."""
  if counts is None:
    return None
  return float(sum(counts[r, c] for r, c in best_assignment(counts)) / total)


def agreement(demos: Demonstration, view: LevelView, level: int, procedures, counters) -> float | None:
  """Fraction of weak demonstrations' elementary steps whose decoded (procedure, counter) at `level` equals
  the supervisor's (None if no weak demonstration carries the supervisor's stack)."""
  return exact_fraction(*agreement_counts(demos, view, level, procedures, counters))


def relabelled_agreement(demos: Demonstration, view: LevelView, level: int, procedures,
                         counters) -> float | None:
  """agreement() under the renaming of decoded procedures that maximises it: how close the segmentation is
  to the supervisor's when the procedures' ids are arbitrary (weak-only training)."""
  return relabelled_fraction(*agreement_counts(demos, view, level, procedures, counters))


def stack_agreement(procedures, counters, decoded_procedures, decoded_counters,
                    level: int) -> tuple[float, float] | None:
  """(exact, up to renaming) fraction of the annotated steps of given stacks [..., T, d] (UNKNOWN where not
  annotated, or padding) whose decoded frame at level equals the given one; None if no step is annotated
  there."""
  procs, taus = np.asarray(procedures)[..., level], np.asarray(counters)[..., level]
  decoded_procs, decoded_taus = np.asarray(decoded_procedures)[..., level], np.asarray(decoded_counters)[..., level]
  known = procs != UNKNOWN
  if not known.any():
    return None
  size = int(max(procs.max(), decoded_procs.max())) + 1
  counts = np.zeros((size, size), np.int64)
  same_tau = known & (decoded_taus == taus)
  np.add.at(counts, (decoded_procs[same_tau], procs[same_tau]), 1)
  return exact_fraction(counts, known.sum()), relabelled_fraction(counts, known.sum())


def stack_procedure_agreement(procedures, decoded_procedures, level: int) -> float | None:
  """The fraction of the annotated steps of given stacks [..., T, d] (UNKNOWN where not annotated, or
  padding) whose decoded procedure at level, renamed one to one (`label_agreement`), is the given one,
  whatever the counters; None if no step is annotated there."""
  procs = np.asarray(procedures)[..., level]
  known = procs != UNKNOWN
  if not known.any():
    return None
  return label_agreement(procs[known], np.asarray(decoded_procedures)[..., level][known])[0]


def stack_boundary_scores(procedures, counters, decoded_procedures, decoded_counters, length,
                          level: int) -> dict | None:
  """boundary_scores of the calls at level that decoded stacks [B, T, d] start against those of the given
  stacks [B, T, d], over the demonstrations (of lengths [B]) whose given stack is known down to level; None
  if there is none."""
  known = known_call_boundaries(procedures, counters, length, level)
  found = [boundary_steps(call_starts(np.asarray(decoded_procedures)[b, :np.asarray(length)[b]],
                                      np.asarray(decoded_counters)[b, :np.asarray(length)[b]], level))
           for b, _ in known]
  return boundary_scores([truth for _, truth in known], found) if known else None


def known_call_boundaries(procedures, counters, length, level: int) -> list[tuple[int, set[int]]]:
  """(b, its call boundaries at level) for each demonstration b of stacks [B, T, d] (lengths [B]) whose stack
  is known down to level (`call_starts`, `boundary_steps`)."""
  procedures, counters = np.asarray(procedures), np.asarray(counters)
  known = []
  for b, n in enumerate(np.asarray(length)):
    given = procedures[b, :n, :level + 1], counters[b, :n, :level + 1]
    if np.all(given[0] != UNKNOWN) and np.all(given[1] != UNKNOWN):
      known.append((b, boundary_steps(call_starts(*given, level))))
  return known


def call_starts(procedures, counters, level: int) -> np.ndarray:
  """[T] bool: the steps where a new call starts at `level`, from one demonstration's stack [T, d] (root
  first). Step 0 starts one; a later step starts one when a level above `level` resumed there, that is when
  some frame above `level` differs from the step before. (A counter of 0 at consecutive steps is no new call:
  the level below took both.) Raises ValueError if a frame at or above `level` is unknown."""
  procedures, counters = np.asarray(procedures), np.asarray(counters)
  if procedures.ndim != 2 or procedures.shape != counters.shape or not 1 <= level < procedures.shape[1]:
    raise ValueError(f"need a stack [T, d] with 1 <= level < d; got {list(procedures.shape)}, level {level}")
  if np.any(procedures[:, :level + 1] == UNKNOWN) or np.any(counters[:, :level + 1] == UNKNOWN):
    raise ValueError(f"the stack is not known down to level {level}")
  return call_tree.call_starts(procedures, counters)[:, level]


def boundary_steps(starts) -> set[int]:
  """The boundaries of a [T] bool of call (or segment) starts: every start after step 0."""
  return {int(t) for t in np.flatnonzero(np.asarray(starts)) if t > 0}


def boundary_scores(true_boundaries, predicted_boundaries, tolerance: int = 0) -> dict:
  """Precision, recall and F1 of predicted boundary steps, pooled over demonstrations: two lists (one entry
  per demonstration) of sets of steps. A predicted boundary is a hit when it is within `tolerance` steps of
  a true one, each true one matched at most once (tolerance 0: the same step; the most hits in each
  demonstration, by best_assignment). Empty ratios: precision 1 with nothing predicted, recall 1 with
  nothing to find; F1 0 when both are 0."""
  if len(true_boundaries) != len(predicted_boundaries):
    raise ValueError(f"{len(true_boundaries)} true and {len(predicted_boundaries)} predicted demonstrations")
  hits = num_true = num_predicted = 0
  for truth, predicted in zip(true_boundaries, predicted_boundaries):
    truth, predicted = sorted(set(truth)), sorted(set(predicted))
    num_true, num_predicted = num_true + len(truth), num_predicted + len(predicted)
    near = np.abs(np.subtract.outer(predicted, truth)) <= tolerance if predicted and truth else np.zeros((0, 0))
    hits += int(sum(near[p, t] for p, t in best_assignment(near)))
  precision = hits / num_predicted if num_predicted else 1.0
  recall = hits / num_true if num_true else 1.0
  f1 = 2 * precision * recall / (precision + recall) if precision + recall else 0.0
  return {"precision": precision, "recall": recall, "f1": f1, "hits": hits, "true": num_true,
          "predicted": num_predicted}


def best_assignment(score) -> list[tuple[int, int]]:
  """The one-to-one assignment of rows to columns of a score matrix [R, C] that maximizes the summed score
  (min(R, C) pairs (row, column), by row): the Hungarian algorithm (O(n^2 m)), in numpy."""
  score = np.asarray(score, np.float64)
  if score.ndim != 2:
    raise ValueError(f"need a matrix; got shape {list(score.shape)}")
  if min(score.shape) == 0:
    return []
  transposed = score.shape[0] > score.shape[1]
  cost = -(score.T if transposed else score)  # rows ≤ columns, minimized
  n, m = cost.shape
  u, v = np.zeros(n + 1), np.zeros(m + 1)
  owner, way = np.zeros(m + 1, int), np.zeros(m + 1, int)  # owner[j]: the row (1-based) holding column j
  for i in range(1, n + 1):
    owner[0], j0 = i, 0
    min_v, used = np.full(m + 1, np.inf), np.zeros(m + 1, bool)
    while True:
      used[j0] = True
      i0, free = owner[j0], np.flatnonzero(~used)
      reduced = cost[i0 - 1, free - 1] - u[i0] - v[free]
      better = reduced < min_v[free]
      min_v[free[better]], way[free[better]] = reduced[better], j0
      j1 = free[np.argmin(min_v[free])]
      delta = min_v[j1]
      u[owner[used]] += delta
      v[used] -= delta
      min_v[~used] -= delta
      j0 = j1
      if owner[j0] == 0:
        break
    while j0:
      j1 = way[j0]
      owner[j0] = owner[j1]
      j0 = j1
  pairs = [(int(owner[j]) - 1, j - 1) for j in range(1, m + 1) if owner[j]]
  return sorted((c, r) for r, c in pairs) if transposed else sorted(pairs)


def label_agreement(true_labels, predicted_labels) -> tuple[float, dict]:
  """(fraction of positions whose predicted label, renamed, equals the true one; the renaming {predicted:
  true}) under the one-to-one renaming of predicted labels to true ones that maximizes it. Labels are any
  integers; a predicted label left without a partner (more predicted labels than true ones) counts as
  wrong. Raises ValueError on empty or mismatched inputs."""
  true_labels, predicted_labels = np.asarray(true_labels).ravel(), np.asarray(predicted_labels).ravel()
  if true_labels.shape != predicted_labels.shape or not true_labels.size:
    raise ValueError(f"need equally many labels, at least one; got {true_labels.size} and {predicted_labels.size}")
  true_ids, true_index = np.unique(true_labels, return_inverse=True)
  predicted_ids, predicted_index = np.unique(predicted_labels, return_inverse=True)
  counts = np.zeros((len(predicted_ids), len(true_ids)), np.int64)
  np.add.at(counts, (predicted_index, true_index), 1)
  pairs = best_assignment(counts)
  hits = sum(int(counts[r, c]) for r, c in pairs)
  return hits / true_labels.size, {int(predicted_ids[r]): int(true_ids[c]) for r, c in pairs}
