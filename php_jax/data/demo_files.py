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
   "hidden": [64],                            optional: hidden layer sizes of every network
   "tau_in_termination": [false, true, true], optional: per level, root first, whether the termination
                                              network sees the counter (`--tau_in_termination`)
   "tau_limit": [0, 1, null],                 optional: per level, root first, the networks see
                                              min(counter, limit), null: the counter (`--tau_limit`)
   "calls": [null, {"p1": ["q1", "q2"]},      optional: per level, root first, null or which operations
             {"q1": [0, 1]}]}                 procedures may take: callees by name, or at the lowest level
                                              each action factor's values (ints where there is one factor);
                                              a procedure not named may take any
   "action_names": [["left", "right"], ...]}  optional: per action factor, a name for each of its values
                                              (what `experiments.show` prints and draws)

A hierarchy file holds at most MAX_COUNT levels, action factors and hidden layers, and at most MAX_SIZE
procedures per level, values per action factor, units per layer and counters per level. Lines and files are
read by php_jax.data.json_lines (its bounds: length, nesting, numbers within float32's range, no repeated keys);
observations must be real numbers (not booleans), actions, procedures and counters integers. Every reader
raises DemoFileError with "PATH:LINE: what is wrong" at the first problem. For large data sets the same
demonstrations can be a binary set (a directory, `php_jax.data.shards`): `read_demonstrations` reads either.
"""
from __future__ import annotations

import dataclasses
import json
import os
from collections.abc import Iterable, Iterator

import numpy as np

from php_jax import encoders
from php_jax.data import files, json_lines, shards
from php_jax.data.demo_checks import (DemoFileError, action_error, check_stack, counter_error, fitted_spec,
                                      observation_size_error)
from php_jax.demos import UNKNOWN, Demonstration, compacted
from php_jax.hierarchy import HierarchySpec

HIERARCHY_KEYS = ("levels", "action_sizes", "name", "capacity", "hidden", "tau_in_termination", "tau_limit", "calls",
                  "observes", "action_names", "observation")
DEMONSTRATION_KEYS = ("observations", "actions", "stack")
MAX_COUNT = 64
MAX_SIZE = 4096


@dataclasses.dataclass(frozen=True)
class Hierarchy:
  """A hierarchy file's contents.

  Attributes:
    spec: the levels and action factor sizes (obs_dim 0: the demonstrations say).
    capacity: per level, root first, the least counter capacity (None where derived); None: derived.
    hidden: hidden layer sizes of every network; None: the default.
    action_names: per action factor, the names of its values; None: not named.
    tau_in_termination: per level, root first, whether the termination network sees the counter; None: the
      default.
    tau_limit: per level, root first, the networks see min(τ, limit) (None: τ itself); None: the default.
  """
  spec: HierarchySpec
  capacity: tuple[int | None, ...] | None
  hidden: tuple[int, ...] | None
  action_names: tuple[tuple[str, ...], ...] | None = None
  tau_in_termination: tuple[bool, ...] | None = None
  tau_limit: tuple[int | None, ...] | None = None


def _is_int(x) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def _is_size(x) -> bool:
  return _is_int(x) and 1 <= x <= MAX_SIZE


def read_hierarchy(path: str) -> Hierarchy:
  """Parses a hierarchy file. Raises DemoFileError naming the file and the problem."""
  try:
    with open(path, "rb") as f:
      obj = json_lines.loads(f.read(json_lines.MAX_LINE_BYTES + 1))
  except (OSError, ValueError) as e:  # not UTF-8, not JSON, or outside json_lines' bounds
    raise DemoFileError(f"{path}: cannot read a hierarchy: {e}") from None
  try:
    return _hierarchy(obj, os.path.splitext(os.path.basename(path))[0])
  except ValueError as e:
    raise DemoFileError(f"{path}: {e}") from None


def _hierarchy(obj, default_name: str) -> Hierarchy:
  if not isinstance(obj, dict):
    raise ValueError("a hierarchy must be a JSON object")
  json_lines.check_keys(obj, HIERARCHY_KEYS, "hierarchy")
  levels, sizes = obj.get("levels"), obj.get("action_sizes")
  if not (isinstance(levels, list) and 2 <= len(levels) <= MAX_COUNT and all(
      isinstance(level, list) and 1 <= len(level) <= MAX_SIZE and all(isinstance(n, str) and n for n in level)
      for level in levels)):
    raise ValueError(f'"levels" must list at least two levels (at most {MAX_COUNT}), root first, each a non-empty '
                     f'list of names (at most {MAX_SIZE})')
  if len(levels[0]) != 1:
    raise ValueError(f'"levels": the root level has one procedure; got {json_lines.shown(levels[0])}')
  for i, level in enumerate(levels):
    if len(set(level)) != len(level):
      raise ValueError(f'"levels": level {i} repeats a name: {json_lines.shown(level)}')
  if not (isinstance(sizes, list) and 1 <= len(sizes) <= MAX_COUNT and all(map(_is_size, sizes))):
    raise ValueError(f'"action_sizes" must list positive integers (at most {MAX_SIZE}), one per action factor '
                     f'(at most {MAX_COUNT}); got {json_lines.shown(sizes)}')
  name = obj.get("name", default_name)
  if not (isinstance(name, str) and name):
    raise ValueError('"name" must be a non-empty string')
  capacity = obj.get("capacity")
  if capacity is not None and not (isinstance(capacity, list) and len(capacity) == len(levels) and all(
      c is None or _is_size(c) for c in capacity)):
    raise ValueError(f'"capacity" must give one positive integer (at most {MAX_SIZE}) or null per level, root '
                     f'first ({len(levels)}); got {json_lines.shown(capacity)}')
  hidden = obj.get("hidden")
  if hidden is not None and not (isinstance(hidden, list) and 1 <= len(hidden) <= MAX_COUNT
                                 and all(map(_is_size, hidden))):
    raise ValueError(f'"hidden" must list positive layer sizes (at most {MAX_SIZE}, at most {MAX_COUNT} layers); '
                     f'got {json_lines.shown(hidden)}')
  tau_in_termination, tau_limit = obj.get("tau_in_termination"), obj.get("tau_limit")
  if tau_in_termination is not None and not (isinstance(tau_in_termination, list) and len(tau_in_termination)
                                             == len(levels) and all(isinstance(v, bool) for v in tau_in_termination)):
    raise ValueError(f'"tau_in_termination" must give one true or false per level, root first ({len(levels)}); '
                     f'got {json_lines.shown(tau_in_termination)}')
  if tau_limit is not None and not (isinstance(tau_limit, list) and len(tau_limit) == len(levels) and all(
      v is None or _is_int(v) and 0 <= v <= MAX_SIZE for v in tau_limit)):
    raise ValueError(f'"tau_limit" must give one integer (0 to {MAX_SIZE}) or null per level, root first '
                     f'({len(levels)}); got {json_lines.shown(tau_limit)}')
  spec = HierarchySpec(name, tuple(tuple(level) for level in levels), tuple(sizes), 0)
  if obj.get("calls") is not None:
    spec = dataclasses.replace(spec, allowed_ops=_declared_calls(obj["calls"], spec))
  if obj.get("observes") is not None:
    spec = dataclasses.replace(spec, observes=_declared_observes(obj["observes"], spec))
  if obj.get("observation") is not None:
    spec = dataclasses.replace(spec, observation=encoders.from_json(obj["observation"]))
  names = obj.get("action_names")
  if names is not None and not (isinstance(names, list) and len(names) == len(sizes) and all(
      isinstance(factor, list) and len(factor) == size and all(isinstance(n, str) and n for n in factor)
      for factor, size in zip(names, sizes))):
    raise ValueError(f'"action_names" must give, per action factor ({len(sizes)}), one non-empty name for each '
                     f'of its values ({json_lines.shown(sizes)}); got {json_lines.shown(names)}')
  return Hierarchy(spec, tuple(capacity) if capacity else None, tuple(hidden) if hidden else None,
                   tuple(map(tuple, names)) if names else None,
                   None if tau_in_termination is None else tuple(tau_in_termination),
                   None if tau_limit is None else tuple(tau_limit))


def action_namer(action_names: tuple[tuple[str, ...], ...] | None):
  """An elementary action (a list of ints, one per factor) → its text: the factors' names joined by spaces,
  or without names the index (one factor) or the list of indices."""
  def name(action: list[int]) -> str:
    if action_names:
      return " ".join(names[a] for names, a in zip(action_names, action))
    return str(action[0]) if len(action) == 1 else str(list(action))
  return name


def _named_procedures(value, key: str, spec: HierarchySpec):
  """(level, procedure index, name, its entry) for each procedure that a per-level hierarchy key ("calls",
  "observes": one object or null per level, root first) names, in order; ValueError naming the key for a
  value of another shape or a procedure its level does not have."""
  depth = spec.num_levels
  if not (isinstance(value, list) and len(value) == depth and all(v is None or isinstance(v, dict) for v in value)):
    raise ValueError(f'"{key}" must give one object or null per level, root first ({depth}); got '
                     f'{json_lines.shown(value)}')
  for level, named in enumerate(value):
    names = spec.levels[level]
    for procedure, entry in (named or {}).items():
      if procedure not in names:
        raise ValueError(f'"{key}": level {level} has no procedure {procedure!r}')
      yield level, names.index(procedure), procedure, entry


def _declared_calls(calls, spec: HierarchySpec) -> tuple:
  """A hierarchy file's "calls" as a call graph (`HierarchySpec.allowed_ops`); ValueError saying what is wrong."""
  graph = [None] * spec.num_levels
  for level, index, procedure, ops in _named_procedures(calls, "calls", spec):
    if graph[level] is None:
      graph[level] = np.ones((spec.num_procs(level), sum(spec.op_sizes(level))), bool)
    graph[level][index] = _allowed_row(ops, level, spec, f'"calls": {procedure!r}')
  return tuple(None if allowed is None else tuple(map(tuple, allowed.tolist())) for allowed in graph)


def _declared_observes(observes, spec: HierarchySpec) -> tuple | None:
  """A hierarchy file's "observes" (per level, root first, an object or null: procedure name → the
  observation entries its networks see) as `HierarchySpec.observes` (None where it names no procedure);
  ValueError saying what is wrong."""
  declared = [None] * spec.num_levels
  for level, index, procedure, indices in _named_procedures(observes, "observes", spec):
    if not (isinstance(indices, list) and len(indices) <= MAX_SIZE
            and all(_is_int(i) and 0 <= i < MAX_SIZE for i in indices)):
      raise ValueError(f'"observes": {procedure!r} must list observation entries (at most {MAX_SIZE} '
                       f'integers, each from 0 to {MAX_SIZE - 1}); got {json_lines.shown(indices)}')
    if declared[level] is None:
      declared[level] = [None] * spec.num_procs(level)
    declared[level][index] = tuple(sorted(set(indices)))
  if all(entries is None for entries in declared):
    return None
  return tuple(None if entries is None else tuple(entries) for entries in declared)


def _allowed_row(ops, level: int, spec: HierarchySpec, where: str) -> np.ndarray:
  """[Σ op_sizes] bools from a procedure's entry in "calls": the callees' names, or at the lowest level the
  allowed values of each action factor (a list of ints where there is one factor)."""
  sizes = spec.op_sizes(level)
  if level < spec.num_levels - 1:
    callees = spec.levels[level + 1]
    if not (isinstance(ops, list) and ops and all(isinstance(c, str) and c in callees for c in ops)):
      raise ValueError(f"{where} must list procedures of level {level + 1} ({', '.join(callees)}); got "
                       f"{json_lines.shown(ops)}")
    return np.isin(np.arange(len(callees)), [callees.index(c) for c in ops])
  values = [ops] if len(sizes) == 1 and isinstance(ops, list) and all(map(_is_int, ops)) else ops
  if not (isinstance(values, list) and len(values) == len(sizes) and all(
      isinstance(v, list) and v and all(_is_int(a) and 0 <= a < n for a in v) for v, n in zip(values, sizes))):
    raise ValueError(f"{where} must list, per action factor, the values it may take (0..size-1; one list of "
                     f"ints where there is one factor); got {json_lines.shown(ops)}")
  return np.concatenate([np.isin(np.arange(n), v) for v, n in zip(values, sizes)])


def write_hierarchy(path: str, spec: HierarchySpec, tau_in_termination: tuple[bool, ...] | None = None,
                    tau_limit: tuple[int | None, ...] | None = None) -> None:
  """Writes spec as a hierarchy file (the inverse of read_hierarchy, less the optional keys but the counter's
  settings where given)."""
  obj = {"name": spec.name, "levels": [list(level) for level in spec.levels], "action_sizes": list(spec.action_sizes),
         **({"tau_in_termination": list(tau_in_termination)} if tau_in_termination is not None else {}),
         **({"tau_limit": list(tau_limit)} if tau_limit is not None else {})}
  files.write_atomically(path, (json.dumps(obj, indent=1) + "\n").encode())


def parse_demonstration(obj, spec: HierarchySpec) -> tuple[np.ndarray, np.ndarray, np.ndarray | None,
                                                            np.ndarray | None]:
  """One line's JSON value as (observations [T+1, D], actions [T, F], procedures, counters [T, d] or None):
  observations of spec.obs_dim numbers (any, where that is 0), actions in spec's sizes, the stack by the
  call-stack rules. Raises ValueError saying what is wrong; a file of another model's hierarchy is told by
  its sizes before any action is judged."""
  if not isinstance(obj, dict):
    raise ValueError("a demonstration must be a JSON object")
  json_lines.check_keys(obj, DEMONSTRATION_KEYS, "demonstration")
  observations, actions = obj.get("observations"), obj.get("actions")
  if not isinstance(actions, list) or not actions:
    raise ValueError('"actions" must be a non-empty list (one elementary action per step)')
  if not (isinstance(observations, list) and len(observations) == len(actions) + 1):
    raise ValueError(f'"observations" must list T+1 = {len(actions) + 1} vectors (one more than the actions)')
  obs = _observations(observations)
  if spec.obs_dim and obs.shape[1] != spec.obs_dim:
    raise observation_size_error(obs.shape[1], spec)
  rows = _actions(actions, spec.action_sizes)
  stack = obj.get("stack")
  procs = taus = None
  if stack is not None:
    procs, taus = _parse_stack(stack, len(actions), spec)
  return obs, rows, procs, taus


def _actions(actions: list, sizes: tuple[int, ...]) -> np.ndarray:
  """[T, F] int32 actions (a bare int stands for a one-factor action); ValueError naming the first action
  that is not F integers, each in its factor's range."""
  rows = []
  for t, action in enumerate(actions):
    action = [action] if _is_int(action) and len(sizes) == 1 else action
    if not (isinstance(action, list) and len(action) == len(sizes) and all(map(_is_int, action))):
      raise ValueError(f"action {t} must be a list of {len(sizes)} integers (one per factor); "
                       f"got {json_lines.shown(action)}")
    for f, (a, size) in enumerate(zip(action, sizes)):
      if not 0 <= a < size:
        raise action_error(t, f, a, sizes)
    rows.append(action)
  return np.array(rows, np.int32)


def _observations(observations: list) -> np.ndarray:
  """[T+1, D] float32 observations; ValueError naming the first that is not D real numbers (booleans are
  not). They are finite in float32: json_lines refuses numbers beyond its range, NaN and infinities."""
  for t, o in enumerate(observations):
    if not (isinstance(o, list) and o and set(map(type, o)) <= {int, float}):
      raise ValueError(f"observation {t} must be a non-empty list of finite numbers (true, false and null are not)")
    if len(o) != len(observations[0]):
      raise ValueError(f"observation {t} has {len(o)} numbers; observation 0 has {len(observations[0])}")
  return np.array(observations, np.float32)


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
        raise ValueError(f"stack step {t}, level {level}: expected [procedure, counter] or null; "
                         f"got {json_lines.shown(frame)}")
      if frame != [UNKNOWN, UNKNOWN]:
        procedure, counter = frame
        if not UNKNOWN <= procedure < spec.num_procs(level):
          raise ValueError(f"stack step {t}: procedure id {procedure} at level {level} is unknown (level "
                           f"{level} has {spec.num_procs(level)} procedures)")
        if not UNKNOWN <= counter <= t + 1:  # stored in int32; check_stack sees the rest
          raise counter_error(t, level, counter)
        procs[t, level], taus[t, level] = frame
  check_stack(procs, taus, spec)
  return procs, taus


def read_demonstrations(path: str, spec: HierarchySpec) -> tuple[Demonstration, HierarchySpec]:
  """All demonstrations of a file as one padded batch [B, ...] (strong = annotated), and spec with the
  observation size the file shows (checked against spec.obs_dim unless that is 0). A directory is read as a
  binary set (`shards`), anything else as JSON lines. Raises DemoFileError at the first bad line (or shard),
  or naming the file if it holds no demonstration."""
  if shards.read_as_binary(path):
    return shards.read_demonstrations(path, spec)
  parsed = list(_json_demonstrations(path, spec))
  return _batch(parsed, spec.num_levels), fitted_spec(path, spec, parsed[0][0].shape[1])


def iter_demonstrations(path: str, spec: HierarchySpec) -> Iterator[shards.Unpadded]:
  """A file's demonstrations one at a time, without padding (`shards.Unpadded`: the stack None where not
  annotated), checked as `read_demonstrations` checks them, holding one line (JSON lines) or one shard (a
  binary set) at a time. Raises DemoFileError as `read_demonstrations` does, when it reaches the problem."""
  demonstrations = (_json_demonstrations(path, spec) if not shards.read_as_binary(path) else
                    (one for batch in shards.iter_shards(path, spec) for one in shards.unpadded(batch, batch.strong)))
  for number, one in enumerate(demonstrations):
    if not number:
      fitted_spec(path, spec, one[0].shape[1])
    yield one


def _json_demonstrations(path: str, spec: HierarchySpec) -> Iterator[shards.Unpadded]:
  """The JSON lines file's demonstrations as `parse_demonstration` gives them, one line at a time; DemoFileError
  at the first bad line, or naming the file if it holds no demonstration."""
  obs_dim, count = spec.obs_dim, 0
  for number, raw in _lines_read(path):
    try:
      one = parse_demonstration(json_lines.loads(raw), spec)
      if obs_dim and one[0].shape[1] != obs_dim:
        raise ValueError(f"observations have {one[0].shape[1]} numbers; expected {obs_dim} (as the first "
                         "demonstration's)")
    except UnicodeDecodeError as e:
      raise DemoFileError(f"{path}:{number}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    except ValueError as e:  # json_lines.JSONSyntaxError and JSONBoundsError included
      raise DemoFileError(f"{path}:{number}: malformed demonstration: {e}") from None
    obs_dim, count = one[0].shape[1], count + 1
    yield one
  if not count:
    raise DemoFileError(f"{path}: no demonstrations")


def _lines_read(path: str) -> Iterator[tuple[int, bytes]]:
  """`json_lines.lines` of the file at path; DemoFileError naming path where it cannot be opened, or a read
  fails partway (a disk error)."""
  try:
    with open(path, "rb") as f:
      yield from json_lines.lines(f)
  except OSError as e:
    raise DemoFileError(f"{path}: cannot read demonstrations: {e.strerror or e}") from None


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
  return compacted(Demonstration(observations, actions, procs, taus,
                                 np.array([len(a) for _, a, _, _ in parsed], np.int32),
                                 np.array([p is not None for _, _, p, _ in parsed])))


def _line(observations: np.ndarray, actions: np.ndarray, procedures: np.ndarray | None,
          counters: np.ndarray | None) -> str:
  """One demonstration (`shards.Unpadded`) as a JSON line, its "stack" where procedures are given."""
  line = {"observations": np.asarray(observations).astype(np.float32).tolist(),
          "actions": np.asarray(actions).tolist()}
  if procedures is not None:
    line["stack"] = [[[int(h), int(tau)] if h != UNKNOWN else None for h, tau in zip(hs, taus)]
                     for hs, taus in zip(procedures, counters)]
  return json.dumps(line)


def write_demonstrations(path: str, batch: Demonstration, annotated, shard_size: int = shards.SHARD_SIZE) -> None:
  """Writes a batch [B, ...] (annotated [B] bool: which carry their "stack") to path whole or not at all: a
  binary set of shard_size demonstrations a shard where path ends in shards.SUFFIX, else JSON lines."""
  write_unpadded(path, shards.unpadded(batch, annotated), shard_size)


def write_unpadded(path: str, demonstrations: Iterable[shards.Unpadded], shard_size: int = shards.SHARD_SIZE) -> None:
  """`write_demonstrations` for demonstrations one at a time (`shards.Unpadded`, as `iter_demonstrations` gives
  them), written as they come: one line, or one shard, held at a time."""
  if shards.write_as_binary(path):
    shards.write_shards(path, demonstrations, shard_size)
  else:
    files.write_streamed(path, ((_line(*one) + "\n").encode() for one in demonstrations))


def read_indices(path: str, count: int) -> list[int]:
  """The distinct "index" of every line of a file (`experiments.suggest`'s output), each in 0..count-1, in the
  file's order. Raises DemoFileError naming the file and line."""
  indices = []
  try:
    f = open(path, "rb")
  except OSError as e:
    raise DemoFileError(f"{path}: cannot read: {e.strerror}") from None
  with f:
    for number, raw in json_lines.lines(f):
      try:
        obj = json_lines.loads(raw)
        index = obj.get("index") if isinstance(obj, dict) else None
        if not (_is_int(index) and 0 <= index < count):
          raise ValueError(f'each line needs an "index" in 0..{count - 1}; got {json_lines.shown(index)}')
        if index in indices:
          raise ValueError(f"index {index} is given twice")
      except ValueError as e:
        raise DemoFileError(f"{path}:{number}: {e}") from None
      indices.append(index)
  if not indices:
    raise DemoFileError(f"{path}: names no demonstration")
  return indices
