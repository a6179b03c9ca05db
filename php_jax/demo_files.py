"""Demonstration and hierarchy files: a user's own data, with no environment code.

A demonstration file is JSON lines, one demonstration per line:

  {"observations": [[float, ...], ...],   T+1 observation vectors o_0 .. o_T, all of one size
   "actions": [[int, ...], ...],          T elementary actions, one index per action factor (a bare int
                                          when there is one factor)
   "stack": [[[h, tau], ...], ...]}       optional: per step, one [procedure, counter] pair per level, root
                                          first; null (or [-1, -1]) where unknown; null for a whole step

A demonstration with a "stack" is annotated (completely or partly), one without is weak. A hierarchy file is
one JSON object:

  {"levels": [["root"], ["p1", "p2"], ...],   procedure names per level, root first (the root alone)
   "action_sizes": [2, 4, 10],                elementary action factor sizes
   "name": "mytask",                          optional (default: the file name without .json)
   "capacity": [null, 8, 3],                  optional: per level, root first, the least counter capacity
                                              below the root (`experiments.fit`'s default: 8)
   "hidden": [64]}                            optional: hidden layer sizes of every network

Every reader raises DemoFileError with "PATH:LINE: what is wrong" at the first problem.
"""
from __future__ import annotations

import dataclasses
import json
import math
import os

import numpy as np

from php_jax import demos as demos_lib
from php_jax.checkpoint import write_atomically
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.task import check_keys

HIERARCHY_KEYS = ("levels", "action_sizes", "name", "capacity", "hidden")
DEMONSTRATION_KEYS = ("observations", "actions", "stack")


class DemoFileError(ValueError):
  """A malformed demonstration or hierarchy file; the message starts with the path (and line)."""


@dataclasses.dataclass(frozen=True)
class Hierarchy:
  """A hierarchy file's contents.

  Attributes:
    spec: the levels and action factor sizes (obs_dim 0: the demonstrations say).
    capacity: per level, root first, the least counter capacity (None where derived); None: derived.
    hidden: hidden layer sizes of every network; None: the default.
  """
  spec: HierarchySpec
  capacity: tuple[int | None, ...] | None
  hidden: tuple[int, ...] | None


def _is_int(x) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def read_hierarchy(path: str) -> Hierarchy:
  """Parses a hierarchy file. Raises DemoFileError naming the file and the problem."""
  try:
    with open(path, "rb") as f:
      obj = json.loads(f.read().decode("utf-8"))
  except (OSError, UnicodeDecodeError, json.JSONDecodeError) as e:
    raise DemoFileError(f"{path}: cannot read a hierarchy: {e}") from None
  try:
    return _hierarchy(obj, os.path.splitext(os.path.basename(path))[0])
  except ValueError as e:
    raise DemoFileError(f"{path}: {e}") from None


def _hierarchy(obj, default_name: str) -> Hierarchy:
  if not isinstance(obj, dict):
    raise ValueError("a hierarchy must be a JSON object")
  check_keys(obj, HIERARCHY_KEYS, "hierarchy")
  levels, sizes = obj.get("levels"), obj.get("action_sizes")
  if not (isinstance(levels, list) and len(levels) >= 2 and all(
      isinstance(level, list) and level and all(isinstance(n, str) and n for n in level) for level in levels)):
    raise ValueError('"levels" must list at least two levels, root first, each a non-empty list of names')
  if len(levels[0]) != 1:
    raise ValueError(f'"levels": the root level has one procedure; got {levels[0]}')
  for i, level in enumerate(levels):
    if len(set(level)) != len(level):
      raise ValueError(f'"levels": level {i} repeats a name: {level}')
  if not (isinstance(sizes, list) and sizes and all(_is_int(n) and n >= 1 for n in sizes)):
    raise ValueError('"action_sizes" must list positive integers, one per action factor')
  name = obj.get("name", default_name)
  if not (isinstance(name, str) and name):
    raise ValueError('"name" must be a non-empty string')
  capacity = obj.get("capacity")
  if capacity is not None and not (isinstance(capacity, list) and len(capacity) == len(levels) and all(
      c is None or (_is_int(c) and c >= 1) for c in capacity)):
    raise ValueError(f'"capacity" must give one positive integer or null per level, root first ({len(levels)})')
  hidden = obj.get("hidden")
  if hidden is not None and not (isinstance(hidden, list) and hidden and all(_is_int(h) and h >= 1 for h in hidden)):
    raise ValueError('"hidden" must list positive layer sizes')
  spec = HierarchySpec(name, tuple(tuple(level) for level in levels), tuple(sizes), 0)
  return Hierarchy(spec, tuple(capacity) if capacity else None, tuple(hidden) if hidden else None)


def write_hierarchy(path: str, spec: HierarchySpec) -> None:
  """Writes spec as a hierarchy file (the inverse of read_hierarchy, less the optional keys)."""
  obj = {"name": spec.name, "levels": [list(level) for level in spec.levels], "action_sizes": list(spec.action_sizes)}
  write_atomically(path, (json.dumps(obj, indent=1) + "\n").encode())


def _parse_line(obj, spec: HierarchySpec) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
  """One line's (observations [T+1, D], actions [T, F], procedures, counters [T, d] or None). ValueError."""
  if not isinstance(obj, dict):
    raise ValueError("a demonstration must be a JSON object")
  check_keys(obj, DEMONSTRATION_KEYS, "demonstration")
  observations, actions = obj.get("observations"), obj.get("actions")
  if not isinstance(actions, list) or not actions:
    raise ValueError('"actions" must be a non-empty list (one elementary action per step)')
  num_factors = len(spec.action_sizes)
  rows = _as_array(actions, "i")
  if rows is not None and rows.ndim == 1 and num_factors == 1:
    rows = rows[:, None]
  if rows is None or rows.ndim != 2 or rows.shape[1] != num_factors:
    _action_error(actions, num_factors)
  bad = np.argwhere((rows < 0) | (rows >= np.array(spec.action_sizes)))
  if bad.size:
    t, f = bad[0]
    raise ValueError(f"action {t}: factor {f} = {rows[t, f]} is outside 0..{spec.action_sizes[f] - 1}")
  if not (isinstance(observations, list) and len(observations) == len(actions) + 1):
    raise ValueError(f'"observations" must list T+1 = {len(actions) + 1} vectors (one more than the actions)')
  obs = _as_array(observations, "if")
  if obs is None or obs.ndim != 2 or not obs.shape[1] or not np.isfinite(obs).all():
    _observation_error(observations)
  stack = obj.get("stack")
  procs = taus = None
  if stack is not None:
    procs, taus = _parse_stack(stack, len(actions), spec)
  return obs.astype(np.float32), rows.astype(np.int32), procs, taus


def _as_array(values: list, kinds: str) -> np.ndarray | None:
  """values as one rectangular NumPy array of a dtype kind in kinds ("i" int, "f" float), or None."""
  try:
    array = np.array(values)
  except ValueError:  # ragged
    return None
  return array if array.dtype.kind in kinds else None


def _action_error(actions: list, num_factors: int):
  """Raises ValueError naming the first action that is not num_factors integers."""
  for t, action in enumerate(actions):
    action = [action] if _is_int(action) and num_factors == 1 else action
    if not (isinstance(action, list) and len(action) == num_factors and all(map(_is_int, action))):
      raise ValueError(f"action {t} must be a list of {num_factors} integers (one per factor); got {action!r}")
  raise ValueError(f"actions must be lists of {num_factors} integers (one per factor)")


def _observation_error(observations: list):
  """Raises ValueError naming the first observation that is not a vector of finite numbers of one size."""
  for t, o in enumerate(observations):
    if not (isinstance(o, list) and o and all(isinstance(x, (int, float)) and not isinstance(x, bool)
                                              and math.isfinite(x) for x in o)):
      raise ValueError(f"observation {t} must be a non-empty list of finite numbers")
    if len(o) != len(observations[0]):
      raise ValueError(f"observation {t} has {len(o)} numbers; observation 0 has {len(observations[0])}")
  raise ValueError("observations must be vectors of finite numbers, all of one size")


def _parse_stack(stack, num_steps: int, spec: HierarchySpec) -> tuple[np.ndarray, np.ndarray]:
  if not (isinstance(stack, list) and len(stack) == num_steps):
    raise ValueError(f'"stack" must give one entry per action ({num_steps}), or be left out')
  depth = spec.num_levels
  procs = np.full((num_steps, depth), UNKNOWN, np.int32)
  taus = np.full((num_steps, depth), UNKNOWN, np.int32)
  for t, frames in enumerate(stack):
    if frames is None:
      continue
    if not (isinstance(frames, list) and len(frames) == depth):
      raise ValueError(f"stack step {t} must list {depth} [procedure, counter] pairs, root first (or be null)")
    for level, frame in enumerate(frames):
      if frame is None:
        continue
      if not (isinstance(frame, list) and len(frame) == 2 and all(map(_is_int, frame))):
        raise ValueError(f"stack step {t}, level {level}: expected [procedure, counter] or null; got {frame!r}")
      if frame != [UNKNOWN, UNKNOWN]:
        procs[t, level], taus[t, level] = frame
  error = demos_lib.stack_error(procs, taus, spec)
  if error:
    raise ValueError(f"stack {error}")
  return procs, taus


def read_demonstrations(path: str, spec: HierarchySpec) -> tuple[Demonstration, HierarchySpec]:
  """All demonstrations of a file as one padded batch [B, ...] (strong = annotated), and spec with the
  observation size the file shows (checked against spec.obs_dim unless that is 0). Raises DemoFileError at
  the first bad line, or naming the file if it holds no demonstration."""
  parsed = []
  try:
    f = open(path, "rb")
  except OSError as e:
    raise DemoFileError(f"{path}: cannot read demonstrations: {e.strerror}") from None
  obs_dim = spec.obs_dim
  with f:
    for number, raw in enumerate(f, start=1):
      try:
        line = raw.decode("utf-8")
        if not line.strip():
          continue
        one = _parse_line(json.loads(line), spec)
        if obs_dim and one[0].shape[1] != obs_dim:
          raise ValueError(f"observations have {one[0].shape[1]} numbers; expected {obs_dim}"
                           + ("" if parsed else " (the model's observation size)"))
        obs_dim = one[0].shape[1]
        parsed.append(one)
      except UnicodeDecodeError as e:
        raise DemoFileError(f"{path}:{number}: not UTF-8 text ({e.reason} at byte {e.start})") from None
      except ValueError as e:  # json.JSONDecodeError included
        raise DemoFileError(f"{path}:{number}: malformed demonstration: {e}") from None
  if not parsed:
    raise DemoFileError(f"{path}: no demonstrations")
  return _batch(parsed, spec.num_levels), HierarchySpec(spec.name, spec.levels, spec.action_sizes, obs_dim)


def _batch(parsed: list, depth: int) -> Demonstration:
  """Pads parsed lines into one Demonstration batch."""
  num, width = len(parsed), max(len(actions) for _, actions, _, _ in parsed)
  obs_dim, num_factors = parsed[0][0].shape[1], parsed[0][1].shape[1]
  observations = np.zeros((num, width + 1, obs_dim), np.float32)
  actions = np.zeros((num, width, num_factors), np.int32)
  procs = np.full((num, width, depth), UNKNOWN, np.int32)
  taus = np.full((num, width, depth), UNKNOWN, np.int32)
  for b, (o, a, p, c) in enumerate(parsed):
    observations[b, :len(o)], actions[b, :len(a)] = o, a
    if p is not None:
      procs[b, :len(a)], taus[b, :len(a)] = p, c
  return Demonstration(observations, actions, procs, taus, np.array([len(a) for _, a, _, _ in parsed], np.int32),
                       np.array([p is not None for _, _, p, _ in parsed]))


def demonstration_lines(batch: Demonstration, annotated) -> list[str]:
  """JSON lines of a batch [B, ...]; annotated [B] bool says which carry their "stack"."""
  lines = []
  obs, actions = np.asarray(batch.observations), np.asarray(batch.actions)
  procs, taus = np.asarray(batch.procedures), np.asarray(batch.counters)
  for b, n in enumerate(np.asarray(batch.length)):
    line = {"observations": obs[b, :n + 1].tolist(), "actions": actions[b, :n].tolist()}
    if annotated[b]:
      line["stack"] = [[[int(h), int(tau)] if h != UNKNOWN else None for h, tau in zip(procs[b, t], taus[b, t])]
                       for t in range(n)]
    lines.append(json.dumps(line))
  return lines
