"""Which procedures may call which: every call allowed, or the calls the annotated demonstrations show.

A call graph is a tuple with one entry per level, root first: for a level that calls procedures, [K_i][K_{i+1}]
bools (whether procedure h may call h'); for the lowest level, and for a level with every call allowed, None.
The networks (`model.PHPLevel`) give a call outside it probability 0, in training, decoding and execution.
"""
from __future__ import annotations

import numpy as np

from php_jax.demos import UNKNOWN, Demonstration
from php_jax.hierarchy import HierarchySpec

CALL_GRAPHS = ("all", "annotated")


def from_annotation(demos: Demonstration, spec: HierarchySpec) -> tuple:
  """The call graph the strongly supervised demonstrations of demos [B, ...] show: a procedure that they show
  calling anything may call only what they show it calling; a procedure never shown calling, or never shown
  being called, is unrestricted. (With no annotation at all: every call allowed.)"""
  procs = np.asarray(demos.procedures)[np.asarray(demos.strong)]  # [B_strong, T, d]
  graph = []
  for level in range(spec.num_levels - 1):
    caller, callee = procs[..., level].ravel(), procs[..., level + 1].ravel()
    known = (caller != UNKNOWN) & (callee != UNKNOWN)
    seen = np.zeros((spec.num_procs(level), spec.num_procs(level + 1)), bool)
    seen[caller[known], callee[known]] = True
    allowed = seen | ~seen.any(axis=1, keepdims=True) | ~seen.any(axis=0, keepdims=True)
    graph.append(None if allowed.all() else tuple(map(tuple, allowed.tolist())))
  return (*graph, None)


def check(demos: Demonstration, spec: HierarchySpec, graph: tuple) -> None:
  """Raises ValueError naming the first strongly supervised demonstration and step whose (partial) annotation
  no chain of calls within graph fits."""
  strong = np.flatnonzero(np.asarray(demos.strong))
  procs = np.asarray(demos.procedures)[strong]  # [B_strong, T, d]; padding is UNKNOWN, so it always fits
  reachable = np.ones(procs.shape[:2] + (1,), bool)  # [B_strong, T, K_level]: the root
  for level in range(1, spec.num_levels):
    allowed = graph[level - 1]
    allowed = np.ones((reachable.shape[-1], spec.num_procs(level)), bool) if allowed is None else np.asarray(allowed)
    reachable = (reachable[..., :, None] & allowed).any(axis=-2)
    known = procs[..., level, None]
    reachable &= (known == UNKNOWN) | (np.arange(spec.num_procs(level)) == known)
    stuck = np.argwhere(~reachable.any(axis=-1))
    if stuck.size:
      n, t = stuck[0]
      raise ValueError(f"demonstration {strong[n]}, step {t}: no chain of calls that the annotated call graph "
                       f"allows fits its annotation at level {level}; allow every call (call_graph 'all')")


def resolve(name: str, demos: Demonstration, spec: HierarchySpec) -> tuple:
  """The call graph `name` (one of CALL_GRAPHS) asks for, for training on demos; ValueError as `check`."""
  if name == "all":
    return (None,) * spec.num_levels
  graph = from_annotation(demos, spec)
  check(demos, spec, graph)
  return graph
