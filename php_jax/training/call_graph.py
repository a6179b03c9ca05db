"""Which operations each procedure may take: any, those the hierarchy declares, or those the annotated
demonstrations show it taking.

A call graph is a tuple with one entry per level, root first: [K_i][Σ op_sizes(i)] bools, per procedure the
values of each operation factor it may take (for a level that calls procedures, its callees; for the lowest
level, the values of each elementary action factor), or None where every operation is allowed. The networks
(`model.PHPLevel`) give an operation outside it probability 0, in training, decoding and execution.
"""
from __future__ import annotations

import dataclasses

import numpy as np

from php_jax.demos import UNKNOWN, Demonstration
from php_jax.hierarchy import HierarchySpec

# all: every operation allowed; calls: the calls the annotation shows; operations: those and the lowest
# level's elementary actions it shows.
CALL_GRAPHS = ("all", "calls", "operations")


def from_annotation(demos: Demonstration, spec: HierarchySpec, actions: bool = True) -> tuple:
  """The call graph the strongly supervised demonstrations of demos [B, ...] show (with actions=False, the
  lowest level's entry is None: its elementary actions unrestricted). Per operation factor, a procedure shown
  taking an operation may take only the values it is shown taking; a procedure never shown, and a value no
  procedure is shown taking, are unrestricted. (With no annotation: every operation allowed.)"""
  strong = np.asarray(demos.strong)
  procs, taken = np.asarray(demos.procedures)[strong], np.asarray(demos.actions)[strong]
  graph = []
  for level in range(spec.num_levels - (not actions)):
    ops = procs[..., level + 1, None] if level < spec.num_levels - 1 else taken  # padding's callers are UNKNOWN
    factors = []
    for f, size in enumerate(spec.op_sizes(level)):
      caller, value = procs[..., level].ravel(), ops[..., f].ravel()
      known = (caller != UNKNOWN) & (value != UNKNOWN)
      seen = np.zeros((spec.num_procs(level), size), bool)
      seen[caller[known], value[known]] = True
      factors.append(seen | ~seen.any(axis=1, keepdims=True) | ~seen.any(axis=0, keepdims=True))
    allowed = np.concatenate(factors, axis=1)
    graph.append(None if allowed.all() else tuple(map(tuple, allowed.tolist())))
  return (*graph, *[None] * (not actions))


def check(demos: Demonstration, spec: HierarchySpec, graph: tuple) -> None:
  """Raises ValueError naming the first demonstration and step that no chain of calls within graph fits
  (`first_unfit`)."""
  unfit = first_unfit(demos, spec, graph)
  if unfit:
    n, t, level = unfit
    raise ValueError(f"demonstration {n}, step {t}: no chain of calls that the call graph allows fits its "
                     f"annotation and elementary action (at level {level}); allow more operations (the "
                     "hierarchy's \"calls\", or call_graph=all)")


def first_unfit(demos: Demonstration, spec: HierarchySpec, graph: tuple) -> tuple[int, int, int] | None:
  """(demonstration, step, level) of the first step that no chain of calls within graph fits: one from the
  root down to a lowest procedure that may take the step's elementary action, through the procedures the
  step's (complete, partial or absent) annotation names; level: where the chain breaks. None where every
  step fits."""
  strong = np.asarray(demos.strong)[:, None, None]
  procs = np.where(strong, np.asarray(demos.procedures), UNKNOWN)  # [B, T, d]
  actions = np.asarray(demos.actions)                              # [B, T, F]
  padding = np.arange(actions.shape[1])[None, :] >= np.asarray(demos.length)[:, None]
  reachable = np.ones(procs.shape[:2] + (1,), bool)  # [B, T, K_level]: the root
  for level in range(spec.num_levels):
    if level:
      calls = graph[level - 1]
      calls = (np.ones((reachable.shape[-1], spec.num_procs(level)), bool) if calls is None
               else np.asarray(calls))
      reachable = (reachable[..., :, None] & calls).any(axis=-2)
    known = procs[..., level, None]
    reachable &= (known == UNKNOWN) | (np.arange(spec.num_procs(level)) == known)
    if level == spec.num_levels - 1 and graph[level] is not None:
      allowed, start = np.asarray(graph[level]), 0
      for f, size in enumerate(spec.action_sizes):
        reachable &= allowed[:, start:start + size].T[actions[..., f]]
        start += size
    stuck = np.argwhere(~reachable.any(axis=-1) & ~padding)
    if stuck.size:
      return int(stuck[0][0]), int(stuck[0][1]), level
  return None


@dataclasses.dataclass(frozen=True)
class UnshownPair:
  """Two consecutive elementary actions that actions-only demonstrations take and no annotated one does,
  which the call graph lets no lowest-level procedure take both of: each such step is split between two
  calls, whether or not one procedure should take both.

  Attributes:
    first, second: the two actions, one value per action factor.
    demonstrations: how many actions-only demonstrations take them one after the other.
    example: the first of those (its index in the batch).
  """
  first: tuple[int, ...]
  second: tuple[int, ...]
  demonstrations: int
  example: int


def unshown_pairs(demos: Demonstration, spec: HierarchySpec, graph: tuple) -> list[UnshownPair]:
  """What graph (for demos [B, ...]) may have locked out: the pairs of consecutive actions that split every
  actions-only demonstration showing them, because no lowest-level procedure the graph lets take the first
  may take the second, and that no annotated demonstration shows (where one does, the annotation shows the
  split). Pairs the declared call graph (`spec.allowed_ops`) splits as well are the user's own choice and
  left out. Most shown first."""
  if graph[-1] is None:
    return []
  may_take = _taker(spec, graph[-1])
  declared = spec.allowed_ops and spec.allowed_ops[-1]
  declared_may_take = _taker(spec, declared) if declared else None
  annotated, weak = set(), {}
  for b, (taken, length, strong) in enumerate(zip(np.asarray(demos.actions), np.asarray(demos.length),
                                                  np.asarray(demos.strong))):
    steps = [tuple(int(v) for v in a) for a in taken[:length]]
    pairs = set(zip(steps[:-1], steps[1:]))
    if strong:
      annotated |= pairs
    for pair in () if strong else pairs:
      weak.setdefault(pair, []).append(b)
  split = lambda taker, a, b: not np.any(taker(a) & taker(b))
  found = [UnshownPair(a, b, len(shown), shown[0]) for (a, b), shown in weak.items()
           if (a, b) not in annotated and split(may_take, a, b)
           and not (declared_may_take and split(declared_may_take, a, b))]
  return sorted(found, key=lambda p: (-p.demonstrations, p.first, p.second))


def _taker(spec: HierarchySpec, allowed):
  """action (a tuple of factor values) → [K_{d-1}] bool: which lowest-level procedures `allowed` (that
  level's entry of a call graph) lets take it."""
  allowed = np.asarray(allowed)
  offsets = np.cumsum((0,) + tuple(spec.action_sizes[:-1]))
  return lambda action: allowed[:, offsets + np.asarray(action)].all(axis=1)


def intersect(a: tuple, b: tuple) -> tuple:
  """The call graph allowing what both a and b allow (per level; None allows everything)."""
  return tuple(y if x is None else x if y is None else tuple(tuple(p and q for p, q in zip(u, v))
                                                             for u, v in zip(x, y)) for x, y in zip(a, b))


def restricts(graph: tuple | None) -> bool:
  """Whether a call graph (per level, None: everything allowed) forbids some operation anywhere."""
  return any(g is not None for g in graph or ())


def named(name: str, demos: Demonstration, spec: HierarchySpec) -> tuple:
  """The call graph `name` (one of CALL_GRAPHS) asks for, for training on demos, within the one spec declares
  (`spec.allowed_ops`), unchecked."""
  graph = spec.allowed_ops or (None,) * spec.num_levels
  if name != "all":
    graph = intersect(graph, from_annotation(demos, spec, actions=name == "operations"))
  return graph


def resolve(name: str, demos: Demonstration, spec: HierarchySpec) -> tuple:
  """`named`'s call graph, checked against every step of demos; ValueError as `check`."""
  graph = named(name, demos, spec)
  if restricts(graph):
    check(demos, spec, graph)
  return graph
