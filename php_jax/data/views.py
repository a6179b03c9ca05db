"""Level views of demonstrations (paper §4.2.3), host side.

The level-i view of a demonstration is the sequence of operations that level i's procedures executed: the
level-(i+1) calls (for the lowest level, the elementary actions), each with the observation at the call's
start, then the final observation. A call at level j starts at elementary step t exactly when every counter
at levels ≥ j is 0 at t (a fresh chain of pushes). Strong views come from the annotated stack; weak views
from decoding the trained level below, one level at a time. A partly annotated demonstration's view is
strong at the lowest level and at each level above whose lower levels are all annotated; its unknown
entries are latent.
"""
from __future__ import annotations

from typing import NamedTuple, TypeVar

import jax
import numpy as np
from jax.sharding import Mesh

from php_jax import sharding
from php_jax.demos import UNKNOWN, Demonstration

Batch = TypeVar("Batch", "LevelView", Demonstration)


class LevelView(NamedTuple):
  """Demonstrations as seen by one level [B, ...]. T = padded view length.

  Attributes:
    observations: [B, T+1, obs_dim] observation at each operation's start, then the final observation.
    actions: [B, T, F] int32 the operations (callee procedure ids, or elementary action factors).
    procedures: [B, T] int32 this level's annotated procedure per operation, UNKNOWN where not annotated.
    counters: [B, T] int32 this level's annotated τ per operation, UNKNOWN where not annotated.
    length: [B] int32 operations used.
    times: [B, T] int32 elementary step at which each operation starts (−1 on padding).
    strong: [B] bool whether the annotation may be trained on: the demonstration is annotated (partly or
      completely) and every level below this one is annotated on every step. Unannotated operations of a
      strong view are UNKNOWN and summed over by the lattice.
    real: [B] bool False on the copies that pad a batch, which the loss weighs 0: to a multiple of the
      device count (`device_view`), or to the largest of several seeds' batches (`stack_seeds`).
  """
  observations: np.ndarray
  actions: np.ndarray
  procedures: np.ndarray
  counters: np.ndarray
  length: np.ndarray
  times: np.ndarray
  strong: np.ndarray
  real: np.ndarray


def select(batch: Batch, rows: np.ndarray) -> Batch:
  """batch's rows (LevelView or Demonstration [B, ...]) where rows [B] bool is True, or at rows' indices."""
  return type(batch)(*(np.asarray(x)[rows] for x in batch))


LEAST_BUCKETS, MOST_BUCKETS = 4, 8  # the range `bucket_count` chooses in
MOST_PADDING = 0.25  # the share of the steps computed that `bucket_count` lets be padding


def bucket_count(lengths: np.ndarray) -> int:
  """The fewest length buckets, from LEAST_BUCKETS to MOST_BUCKETS, whose `length_groups` of lengths [B] leave at
  most MOST_PADDING of the steps computed as padding (MOST_BUCKETS where none does). Each bucket is one more
  compiled program, hence the fewest."""
  values, counts = np.unique(np.asarray(lengths), return_counts=True)
  cells, _ = _fewest_padded_cells(values, counts, min(MOST_BUCKETS - 1, len(values)))
  steps = int(np.sum(values * counts))
  for count in range(LEAST_BUCKETS, MOST_BUCKETS):  # more groups than distinct lengths pad nothing
    if 1.0 - steps / cells[min(count, len(values)), len(values)] <= MOST_PADDING:
      return count
  return MOST_BUCKETS


def length_groups(lengths: np.ndarray, num_buckets: int) -> list[tuple[np.ndarray, int]]:
  """The indices of lengths [B] in ascending order of length, split into min(num_buckets, B) groups, each
  padded to its longest: (indices, longest length) per group. The split points leave the fewest padding steps
  in all (exactly: dynamic programming over the distinct lengths, then, where there are fewer distinct lengths
  than groups, the largest groups halved, which pads no more)."""
  order = np.argsort(lengths, kind="stable")
  values, counts = np.unique(np.asarray(lengths)[order], return_counts=True)
  starts = np.concatenate([[0], np.cumsum(counts)])
  ends = _fewest_padded_ends(values, counts, min(num_buckets, len(values)))
  groups = [order[starts[first]:starts[last + 1]] for first, last in zip([0, *(e + 1 for e in ends[:-1])], ends)]
  while len(groups) < min(num_buckets, len(order)):
    largest = max(range(len(groups)), key=lambda g: len(groups[g]))
    groups[largest:largest + 1] = np.array_split(groups[largest], 2)
  return [(group, int(np.asarray(lengths)[group].max())) for group in groups]


def _fewest_padded_ends(values: np.ndarray, counts: np.ndarray, groups: int) -> list[int]:
  """The last distinct-length index of each of `groups` contiguous groups of the sorted distinct lengths
  `values` (each held `counts` times) that minimise Σ group size × its longest length."""
  _, choice = _fewest_padded_cells(values, counts, groups)
  ends, j = [], len(values)
  for g in range(groups, 0, -1):
    ends.append(j - 1)
    j = choice[g, j]
  return ends[::-1]


def _fewest_padded_cells(values: np.ndarray, counts: np.ndarray, groups: int) -> tuple[np.ndarray, np.ndarray]:
  """Dynamic programming over the sorted distinct lengths `values` (each held `counts` times): cells[g, j], the
  fewest steps computed (Σ group size × its longest) that the first j distinct lengths take in g contiguous
  groups, for g ≤ groups; choice[g, j], where the last of those groups starts."""
  n = len(values)
  total = np.concatenate([[0], np.cumsum(counts)])
  cells = np.full((groups + 1, n + 1), np.inf)
  choice = np.zeros((groups + 1, n + 1), int)
  cells[0, 0] = 0.0
  for g in range(1, groups + 1):
    for j in range(g, n + 1):  # group g holds distinct lengths i..j-1, padded to values[j-1]
      costs = cells[g - 1, :j] + (total[j] - total[:j]) * values[j - 1]
      choice[g, j] = int(np.argmin(costs))
      cells[g, j] = costs[choice[g, j]]
  return cells, choice


def padding_fraction(buckets: list[Batch]) -> float:
  """The share of the steps computed over buckets (each bucket's rows × its width) that are padding."""
  computed = sum(int(np.shape(b.actions)[0]) * int(np.shape(b.actions)[1]) for b in buckets)
  return 1.0 - sum(int(np.sum(b.length)) for b in buckets) / computed if computed else 0.0


def length_buckets(batch: Batch, num_buckets: int | None) -> list[Batch]:
  """batch (LevelView or Demonstration [B, ...]) in `length_groups` (`grouped`): num_buckets of them, or where
  None, `bucket_count`'s."""
  lengths = np.asarray(batch.length)
  count = bucket_count(lengths) if num_buckets is None else num_buckets
  return grouped(batch, [group for group, _ in length_groups(lengths, count)])


def grouped(batch: Batch, groups: list[np.ndarray]) -> list[Batch]:
  """batch's rows in groups (index arrays), each group trimmed to its longest: its step arrays ([B, T, ...]) to
  that many steps, its observations to one more."""
  buckets = []
  for group in groups:
    width = int(np.asarray(batch.length)[group].max())
    buckets.append(type(batch)(*(_rows(np.asarray(x), group, width + (name == "observations"))
                                 for name, x in zip(batch._fields, batch))))
  return buckets


def _rows(x: np.ndarray, rows: np.ndarray, width: int) -> np.ndarray:
  """x's rows, their steps (axis 1, where x has one) trimmed to width: a copy of that much alone."""
  return x[rows, :width] if x.ndim >= 2 else x[rows]


def device_view(view: LevelView, mesh: Mesh | None = None) -> LevelView:
  """The view as device arrays, with annotations only on strong demonstrations. With a mesh, padded to a
  multiple of its device count (`sharding.pad`: real False on the copies) and split over its devices along B."""
  view, real = sharding.pad(strong_annotations_only(view), mesh)
  return sharding.put(view._replace(real=view.real & real), mesh)


def device_demonstrations(demos: Demonstration, mesh: Mesh | None = None) -> tuple[Demonstration, jax.Array]:
  """(demos as device arrays with annotations only on strong ones, real [B'] bool): `device_view` for
  demonstrations, which carry no `real` field of their own."""
  return sharding.put(sharding.pad(strong_annotations_only(demos), mesh), mesh)


def demonstration_buckets(demos: Demonstration, num_buckets: int | None,
                          mesh: Mesh | None = None) -> list[tuple[Demonstration, jax.Array]]:
  """`length_buckets` of demos as device arrays (`device_demonstrations`): (batch, real [B]) each."""
  return [device_demonstrations(bucket, mesh) for bucket in length_buckets(demos, num_buckets)]


def training_buckets(batch: Batch, num_buckets: int | None, mesh: Mesh | None = None) -> list:
  """batch's `length_buckets` as one model's training takes them, annotations only on strong rows (a
  Demonstration's bucket as (batch, real [B])): split over mesh's devices (`device_view`,
  `device_demonstrations`), or without a mesh as host arrays, which `fitting.fit` places whole or draws its
  minibatches from."""
  buckets = length_buckets(batch, num_buckets)
  if mesh is not None:
    place = device_view if isinstance(batch, LevelView) else device_demonstrations
    return [place(bucket, mesh) for bucket in buckets]
  if isinstance(batch, LevelView):
    return [strong_annotations_only(bucket) for bucket in buckets]
  return [sharding.pad(strong_annotations_only(bucket), None) for bucket in buckets]


def stack_seeds(buckets: list[list[LevelView]], mesh: Mesh | None = None) -> list[LevelView]:
  """Several seeds' length buckets (buckets[s][i]: seed s's bucket i, as `length_buckets` makes them; every
  seed with as many) → bucket i of every seed stacked [S, B_i, ...] as device arrays, with annotations only on
  strong demonstrations. Each seed's bucket is padded to the longest (width) and largest (B_i, with copies of
  its first view, real False) among the seeds; with a mesh, B_i is a multiple of its device count and the
  buckets are split over its devices along B."""
  if len({len(seed) for seed in buckets}) != 1:
    raise ValueError(f"every seed needs as many length buckets; got {[len(seed) for seed in buckets]}")
  stacked = []
  for group in zip(*buckets):
    size = max(len(b.length) for b in group)
    size += -size % mesh.size if mesh is not None else 0
    width = max(b.actions.shape[1] for b in group)
    padded = [_pad(strong_annotations_only(b), size, width) for b in group]
    stacked.append(sharding.put(LevelView(*(np.stack(x) for x in zip(*padded))), mesh, axis=1))
  return stacked


def strong_annotations_only(batch: Batch) -> Batch:
  """batch (LevelView or Demonstration) with procedures and counters UNKNOWN on every weak entry."""
  strong = np.asarray(batch.strong).reshape(-1, *[1] * (np.ndim(batch.procedures) - 1))
  return batch._replace(procedures=np.where(strong, batch.procedures, UNKNOWN),
                        counters=np.where(strong, batch.counters, UNKNOWN))


def _pad(view: LevelView, size: int, width: int) -> LevelView:
  """view with copies of its first view up to `size` views (real False) and padding steps up to `width`."""
  count = len(view.length)
  view = LevelView(*(np.asarray(x)[np.r_[np.arange(count), np.zeros(size - count, int)]] for x in view))
  extra = width - view.actions.shape[1]

  def steps(x, value):
    return np.pad(x, [(0, 0), (0, extra)] + [(0, 0)] * (x.ndim - 2), constant_values=value)

  return view._replace(observations=steps(view.observations, 0), actions=steps(view.actions, 0),
                       procedures=steps(view.procedures, UNKNOWN), counters=steps(view.counters, UNKNOWN),
                       times=steps(view.times, -1), real=view.real & (np.arange(size) < count))


def _pack(demos: Demonstration, level: int, times: list[np.ndarray], actions: list[np.ndarray]) -> LevelView:
  """Pads per-demonstration operation lists into a LevelView whose annotation is read at `level`."""
  obs, procs, taus = (np.asarray(x) for x in (demos.observations, demos.procedures, demos.counters))
  strong, lengths = np.asarray(demos.strong), np.asarray(demos.length)
  num_demos, width = len(times), max(1, max(len(t) for t in times))
  num_factors = actions[0].shape[1] if actions[0].ndim == 2 else 1
  view = LevelView(
      observations=np.zeros((num_demos, width + 1, obs.shape[-1]), obs.dtype),
      actions=np.zeros((num_demos, width, num_factors), np.int32),
      procedures=np.full((num_demos, width), UNKNOWN, np.int32),
      counters=np.full((num_demos, width), UNKNOWN, np.int32),
      length=np.array([len(t) for t in times], np.int32),
      times=np.full((num_demos, width), -1, np.int32), strong=strong.copy(), real=np.ones(num_demos, bool))
  for b, (t, a) in enumerate(zip(times, actions)):
    # A level's annotation is usable when the levels below are annotated throughout: only then are its
    # operations (their calls) the annotated ones.
    view.strong[b] &= bool(np.all(procs[b, :lengths[b], level + 1:] != UNKNOWN))
    n = len(t)
    view.observations[b, :n] = obs[b, t]
    view.observations[b, n] = obs[b, lengths[b]]
    view.actions[b, :n] = a.reshape(n, num_factors)
    view.times[b, :n] = t
    if strong[b]:
      view.procedures[b, :n] = procs[b, t, level]
      view.counters[b, :n] = taus[b, t, level]
  return view


def lowest_view(demos: Demonstration, num_levels: int) -> LevelView:
  """The lowest level's view: every elementary step, with the annotation at level d−1."""
  lengths = np.asarray(demos.length)
  times = [np.arange(n) for n in lengths]
  actions = [np.asarray(demos.actions)[b, :n] for b, n in enumerate(lengths)]
  return _pack(demos, num_levels - 1, times, actions)


def annotated_views(demos: Demonstration, num_levels: int) -> list[LevelView]:
  """Every level's view, root first, from the demonstrations' own annotation (which must cover every step):
  the views that a right decoding of every level gives."""
  level_views = [lowest_view(demos, num_levels)]
  for level in range(num_levels - 1, 0, -1):
    view = level_views[0]
    level_views.insert(0, view_above(demos, view, level, view.procedures, view.counters))
  return level_views


def view_above(demos: Demonstration, view: LevelView, level: int, procedures: np.ndarray,
               counters: np.ndarray) -> LevelView:
  """The view of level−1 from level's view and level's (annotated or decoded) frames per operation.

  Args:
    demos: the elementary demonstrations the views came from.
    view: level's view.
    level: the level of `view` (≥ 1).
    procedures, counters: [B, T] level's procedure and τ at each of its operations.
  """
  times, actions = [], []
  for b, n in enumerate(view.length):
    starts = np.flatnonzero(counters[b, :n] == 0)  # level's calls start where its counter restarts
    times.append(view.times[b, starts])
    actions.append(procedures[b, starts])
  return _pack(demos, level - 1, times, actions)
