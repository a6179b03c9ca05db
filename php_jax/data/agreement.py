"""How well decoded weak views (or decoded stacks) recover the supervisor's hierarchy: per level, the
fraction of elementary steps whose decoded (procedure, counter) equals the supervisor's, by exact procedure
ids and up to a renaming of them."""
from __future__ import annotations

import itertools

import numpy as np

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
  """Agreement under the best renaming from agreement_counts' result: brute force over the K! renamings,
  so None (not measured) above K = 8, as when no weak demonstration carries the stack."""
  num_procs = 0 if counts is None else len(counts)
  if not 0 < num_procs <= 8:
    return None
  rows = np.arange(num_procs)
  best = max(counts[rows, list(perm)].sum() for perm in itertools.permutations(range(num_procs)))
  return float(best / total)


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
                    level: int) -> tuple[float, float | None] | None:
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
