"""Demonstrations in a binary format for large data sets: a directory of shards with a manifest.

  NAME.shards/
    manifest.json     {"format": FORMAT, "version": 2, "observation_size": D,
                       "shards": [{"file": "shard-00000.npz", "demonstrations": n, "steps": s,
                                   "observations": "uint8", "bytes": b, "sha256": "..."}, ...]}
    shard-00000.npz   a NumPy .npz archive (deflated) of the next shard_size demonstrations, in order:
      observations  [s + n, D]  every demonstration's T+1 observations, one after another, in the narrowest of
                                ENCODINGS that gives back their float32 values bit for bit (the manifest says which)
      actions       [s, F]      int32, every demonstration's T actions, one after another
      lengths       [n]         int32, each demonstration's T ≥ 1 (the offsets into the arrays above)
      annotated     [n]         bool, which demonstrations carry their stack
      procedures    [a, d]      int32, the annotated demonstrations' stacks, one after another (a: their steps;
      counters      [a, d]      [0, 0] where none is annotated), UNKNOWN (-1) for unknown entries

Nothing is padded, and a set reads to the same Demonstration arrays as the JSON lines it was written from
(`demo_files`). Readers refuse, with DemoFileError in one line naming the file: a manifest that is not this
format's, a listed shard that is missing, a file the manifest does not list, a shard whose size or sha256 is
not the manifest's, and, as the JSON reader does, sizes that are not the hierarchy's, actions out of range and
stacks that break the call-stack rules, naming the shard and the demonstration (numbered from 0 across the set).
Each shard is checked as it is read: `iter_shards` reads one at a time.
"""
from __future__ import annotations

import errno
import hashlib
import io
import itertools
import json
import os
import re
import secrets
import shutil
import zipfile
import zlib
from collections.abc import Iterable, Iterator
from typing import NamedTuple

import jax
import numpy as np

from php_jax.data import files, json_lines
from php_jax.data.demo_checks import DemoFileError, action_error, check_stack, fitted_spec, observation_size_error
from php_jax.demos import OBSERVATION_DTYPES, UNKNOWN, Demonstration, compact_dtype
from php_jax.hierarchy import HierarchySpec

SUFFIX = ".shards"  # a writer's path ending in it gets this format
MANIFEST = "manifest.json"
FORMAT = "php_jax demonstration shards"
VERSION = 2  # version 1 knew the encodings uint8, float16 and float32 alone; this reader reads both
READ_VERSIONS = (1, 2)
SHARD_SIZE = 1000
ENCODINGS = OBSERVATION_DTYPES  # narrowest first
COMPRESSION_LEVEL = 1  # zlib's fastest: a third of level 6's writing time, 1.7 times its size (measured)
_MANIFEST_KEYS = ("format", "version", "observation_size", "shards")
_ENTRY_KEYS = ("file", "demonstrations", "steps", "observations", "bytes", "sha256")
_ARRAYS = ("observations", "actions", "lengths", "annotated", "procedures", "counters")
_SHARD_FILE = re.compile(r"shard-[0-9]{5,9}\.npz")
_SHA256 = re.compile(r"[0-9a-f]{64}")

# One demonstration: observations [T+1, D], actions [T, F], and procedures and counters [T, d] or None (not
# annotated); what `demo_files.parse_demonstration` returns.
Unpadded = tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]


class _Ragged(NamedTuple):
  """A shard's demonstrations one after another: observations [Σ(T+1), D] (float32 to write; read: as stored),
  actions [ΣT, F] int32, lengths [n] int32, annotated [n] bool, procedures and counters [Σ annotated T, d] int32."""
  observations: np.ndarray
  actions: np.ndarray
  lengths: np.ndarray
  annotated: np.ndarray
  procedures: np.ndarray
  counters: np.ndarray


def read_as_binary(path: str) -> bool:
  """Whether a reader reads path as this format: a directory (anything else is JSON lines)."""
  return os.path.isdir(path)


def write_as_binary(path: str) -> bool:
  """Whether a writer writes path in this format: its name ends in SUFFIX."""
  return os.path.normpath(path).endswith(SUFFIX)


def is_set(path: str) -> bool:
  """Whether path holds a demonstration set (its manifest, its shards and nothing else), damaged or not."""
  try:
    _manifest(path)
    return True
  except DemoFileError:
    return False


def unpadded(batch: Demonstration, annotated) -> Iterator[Unpadded]:
  """Each demonstration of a padded batch [B, ...] without its padding; annotated [B] bool says which keep
  their stack."""
  obs, actions = np.asarray(batch.observations), np.asarray(batch.actions)
  procs, taus = np.asarray(batch.procedures), np.asarray(batch.counters)
  for b, n in enumerate(np.asarray(batch.length)):
    stack = (procs[b, :n], taus[b, :n]) if annotated[b] else (None, None)
    yield obs[b, :n + 1], actions[b, :n], *stack


# Writing.

def write_shards(path: str, demonstrations: Iterable[Unpadded], shard_size: int = SHARD_SIZE) -> None:
  """Writes demonstrations (an iterable: a generator may make them as they are written, holding one shard's
  worth at a time) as a set at path, shard_size to a shard, whole or not at all: into a fresh directory beside
  path, renamed into place once complete; a set already at path is replaced, and anything else there refused
  (FileExistsError). The fresh directory is listed in files.PARTIAL while filled (an interrupt then deletes
  it) and removed if anything fails (KeyboardInterrupt included); files.WRITING is held for the renames.
  ValueError: no demonstrations, or ones of other shapes than the first's. Of several processes
  (jax.distributed), only the first writes."""
  if not (isinstance(shard_size, int) and shard_size >= 1):
    raise ValueError(f"shard_size must be a positive integer; got {shard_size!r}")
  if jax.process_index() != 0:
    return
  path = os.path.realpath(path)
  _refuse_other_than_a_set(path)
  os.makedirs(os.path.dirname(path), exist_ok=True)
  with files.WRITING:  # an interrupt finds the directory listed as soon as it exists
    fresh, entries = _fresh_directory(path, "tmp"), []
    files.PARTIAL.add(fresh)
  try:
    shape = None
    for number, chunk in enumerate(_chunks(demonstrations, shard_size)):
      entry, shape = _write_shard(fresh, number, chunk, number * shard_size, shape)
      entries.append(entry)
    if shape is None:
      raise ValueError("no demonstrations to write")
    manifest = {"format": FORMAT, "version": VERSION, "observation_size": shape[0], "shards": entries}
    _write_new(os.path.join(fresh, MANIFEST), (json.dumps(manifest, indent=1) + "\n").encode())
    with files.WRITING:
      _refuse_other_than_a_set(path)  # again: something may have come there meanwhile
      _put_in_place(fresh, path)
      files.PARTIAL.discard(fresh)
  except BaseException:
    shutil.rmtree(fresh, ignore_errors=True)
    files.PARTIAL.discard(fresh)
    raise


def _refuse_other_than_a_set(path: str) -> None:
  """FileExistsError where something other than a demonstration set is at path (a set there is replaced)."""
  if os.path.lexists(path) and not is_set(path):
    raise FileExistsError(errno.EEXIST, "something that is not a demonstration set is there; not replaced", path)


def _chunks(items: Iterable, size: int) -> Iterator[list]:
  iterator = iter(items)
  while chunk := list(itertools.islice(iterator, size)):
    yield chunk


def _write_shard(directory: str, number: int, chunk: list, first: int, shape: tuple | None) -> tuple[dict, tuple]:
  """Writes chunk's demonstrations (the first numbered first in the set; shape: as `_joined`'s) as shard
  number; (its manifest entry, the shape)."""
  ragged, shape = _joined(chunk, first, shape)
  encoding = compact_dtype(ragged.observations).name
  data = _archive({**ragged._asdict(), "observations": ragged.observations.astype(encoding)})
  name = f"shard-{number:05d}.npz"
  _write_new(os.path.join(directory, name), data)
  entry = {"file": name, "demonstrations": len(chunk), "steps": len(ragged.actions), "observations": encoding,
           "bytes": len(data), "sha256": hashlib.sha256(data).hexdigest()}
  return entry, shape


def _joined(chunk: list, first: int, shape: tuple | None) -> tuple[_Ragged, tuple]:
  """chunk's demonstrations one after another, and the set's shape so far (observation size, action factors,
  stack levels or 0 before any is annotated; None: take chunk's first's). ValueError naming the first
  demonstration (numbered from first) of another shape, or whose observations are not finite."""
  obs_dim, factors, depth = shape or (np.shape(chunk[0][0])[-1], np.shape(chunk[0][1])[-1], 0)
  depth = depth or next((np.shape(p)[-1] for _, _, p, _ in chunk if p is not None), 0)
  for i, (obs, actions, procs, taus) in enumerate(chunk, first):
    steps = len(actions)
    if not (steps >= 1 and np.shape(obs) == (steps + 1, obs_dim) and np.shape(actions) == (steps, factors)
            and (procs is None and taus is None or np.shape(procs) == np.shape(taus) == (steps, depth))):
      raise ValueError(f"demonstration {i}: observations {np.shape(obs)}, actions {np.shape(actions)} and stack "
                       f"{'none' if procs is None else np.shape(procs)} do not fit [T+1, {obs_dim}], [T, {factors}] "
                       f"and [T, {depth}] with T ≥ 1, as the set's first demonstrations")
    if not np.isfinite(obs).all():
      raise ValueError(f"demonstration {i}: observations must be finite numbers")
  stacks = [(np.asarray(p), np.where(np.asarray(p) == UNKNOWN, UNKNOWN, c)) for _, _, p, c in chunk if p is not None]
  procedures, counters = ([np.concatenate(s).astype(np.int32) for s in zip(*stacks)]
                          or [np.zeros((0, 0), np.int32)] * 2)
  ragged = _Ragged(np.concatenate([o for o, _, _, _ in chunk]).astype(np.float32),
                   np.concatenate([a for _, a, _, _ in chunk]).astype(np.int32),
                   np.array([len(a) for _, a, _, _ in chunk], np.int32),
                   np.array([p is not None for _, _, p, _ in chunk]), procedures, counters)
  return ragged, (obs_dim, factors, depth)


def _archive(arrays: dict[str, np.ndarray]) -> bytes:
  """An .npz archive of arrays (np.load reads it), deflated, with fixed timestamps: the same arrays give the
  same bytes."""
  buffer = io.BytesIO()
  with zipfile.ZipFile(buffer, "w") as archive:
    for name, array in arrays.items():
      npy = io.BytesIO()
      np.lib.format.write_array(npy, np.ascontiguousarray(array), allow_pickle=False)
      archive.writestr(zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0)), npy.getvalue(),
                       compress_type=zipfile.ZIP_DEFLATED, compresslevel=COMPRESSION_LEVEL)
  return buffer.getvalue()


def _fresh_directory(path: str, kind: str) -> str:
  """A new directory beside path (.NAME.RANDOM.kind), with the mode mkdir gives (0o777 & ~umask)."""
  while True:
    fresh = os.path.join(os.path.dirname(path), f".{os.path.basename(path)}.{secrets.token_hex(6)}.{kind}")
    try:
      os.mkdir(fresh, 0o777)
      return fresh
    except FileExistsError:
      continue


def _write_new(path: str, data: bytes) -> None:
  """Writes a new file (mode 0o666 & ~umask, as open() gives it)."""
  with os.fdopen(os.open(path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb") as f:
    f.write(data)


def _put_in_place(fresh: str, path: str) -> None:
  """Renames the directory fresh to path; a set already there is moved aside first and removed after."""
  old = None
  if os.path.lexists(path):
    old = _fresh_directory(path, "old")
    os.rename(path, old)  # onto the empty directory just made
  try:
    os.rename(fresh, path)
  except BaseException:
    if old:
      os.rename(old, path)
    raise
  if old:
    shutil.rmtree(old, ignore_errors=True)


# Reading.

def iter_shards(path: str, spec: HierarchySpec) -> Iterator[Demonstration]:
  """The set's demonstrations, a shard at a time, each shard a padded batch [n, ...] as `read_demonstrations`'
  (padded to the shard's longest, its observations in the shard's own type), checked as it is read. Raises
  DemoFileError naming the file of the first problem (the manifest's before any shard is read)."""
  for ragged in _shards(path, spec):
    yield _padded(ragged, spec.num_levels)


def read_demonstrations(path: str, spec: HierarchySpec) -> tuple[Demonstration, HierarchySpec]:
  """The whole set as one padded batch [B, ...] (strong = annotated), and spec with the set's observation
  size; what `demo_files.read_demonstrations` gives for the JSON lines the set was written from."""
  parts = list(_shards(path, spec))
  joined = _Ragged(*(np.concatenate(arrays) for arrays in zip(*parts)))
  joined = joined._replace(observations=joined.observations.astype(compact_dtype(joined.observations), copy=False))
  return _padded(joined, spec.num_levels), fitted_spec(path, spec, joined.observations.shape[1])


def _shards(path: str, spec: HierarchySpec) -> Iterator[_Ragged]:
  manifest = _manifest(path)
  if spec.obs_dim and manifest["observation_size"] != spec.obs_dim:
    error = observation_size_error(manifest["observation_size"], spec)
    raise DemoFileError(f"{os.path.join(path, MANIFEST)}: {error}")
  first = 0
  for entry in manifest["shards"]:
    yield _shard(os.path.join(path, entry["file"]), entry, manifest["observation_size"], spec, first)
    first += entry["demonstrations"]


def _manifest(path: str) -> dict:
  """The set's manifest, checked, with the directory holding its shards and nothing else."""
  file = os.path.join(path, MANIFEST)
  try:
    with open(file, "rb") as f:
      raw = f.read(json_lines.MAX_LINE_BYTES + 1)
  except FileNotFoundError:
    raise DemoFileError(f"{path}: a directory without {MANIFEST}, so not a demonstration set (a directory is "
                        "read as one, a file as JSON lines)") from None
  except OSError as e:
    raise DemoFileError(f"{file}: cannot read: {e.strerror}") from None
  try:
    manifest = json_lines.loads(raw)
    _check_manifest(manifest)
  except ValueError as e:  # UnicodeDecodeError and json_lines' errors included
    raise DemoFileError(f"{file}: not a demonstration set's manifest: {e}") from None
  listed = [entry["file"] for entry in manifest["shards"]]
  try:
    present = set(os.listdir(path)) - {MANIFEST}
  except OSError as e:
    raise DemoFileError(f"{path}: cannot list its files: {e.strerror}") from None
  missing = [name for name in listed if name not in present]
  if missing:
    raise DemoFileError(f"{os.path.join(path, missing[0])}: missing (the manifest lists it)")
  extra = sorted(present - set(listed))
  if extra:
    raise DemoFileError(f"{os.path.join(path, extra[0])}: not in the manifest (a demonstration set holds its "
                        "manifest and the shards it lists, nothing else)")
  return manifest


def _is_count(value, least: int) -> bool:
  return isinstance(value, int) and not isinstance(value, bool) and value >= least


def _check_manifest(obj) -> None:
  """ValueError saying how obj is not this format's manifest."""
  if not (isinstance(obj, dict) and obj.get("format") == FORMAT):
    raise ValueError(f'its "format" is not {FORMAT!r}')
  json_lines.check_keys(obj, _MANIFEST_KEYS, "manifest")
  if not (_is_count(obj.get("version"), 0) and obj["version"] in READ_VERSIONS):
    raise ValueError(f"version {json_lines.shown(obj.get('version'))}; this php_jax reads versions "
                     f"{' and '.join(map(str, READ_VERSIONS))}")
  if not _is_count(obj.get("observation_size"), 1):
    raise ValueError('"observation_size" must be a positive integer; got '
                     f'{json_lines.shown(obj.get("observation_size"))}')
  entries = obj.get("shards")
  if not (isinstance(entries, list) and entries):
    raise ValueError('"shards" must list the shards, at least one')
  for i, entry in enumerate(entries):
    if not (isinstance(entry, dict) and set(entry) == set(_ENTRY_KEYS) and isinstance(entry["file"], str)
            and _SHARD_FILE.fullmatch(entry["file"]) and _is_count(entry["demonstrations"], 1)
            and _is_count(entry["steps"], entry["demonstrations"]) and entry["observations"] in ENCODINGS
            and _is_count(entry["bytes"], 0) and isinstance(entry["sha256"], str)
            and _SHA256.fullmatch(entry["sha256"])):
      raise ValueError(f'"shards" entry {i} must give {", ".join(_ENTRY_KEYS)} (a shard-NNNNN.npz file, at least one '
                       f"demonstration, at least one step each, one of {', '.join(ENCODINGS)}, a size in bytes and "
                       f"a sha256 in hex); got {json_lines.shown(entry)}")
  names = [entry["file"] for entry in entries]
  if len(set(names)) != len(names):
    raise ValueError('"shards" lists a file twice')


def _shard(file: str, entry: dict, obs_dim: int, spec: HierarchySpec, first: int) -> _Ragged:
  """A shard's demonstrations (the first numbered first in the set), checked against its manifest entry, the
  observation size and spec."""
  try:
    with open(file, "rb") as f:
      size = os.fstat(f.fileno()).st_size
      if size != entry["bytes"]:
        raise DemoFileError(f"{file}: {size} bytes where the manifest says {entry['bytes']} (the file was cut "
                            "short or changed)")
      data = f.read()
  except OSError as e:
    raise DemoFileError(f"{file}: cannot read: {e.strerror}") from None
  if hashlib.sha256(data).hexdigest() != entry["sha256"]:
    raise DemoFileError(f"{file}: its sha256 differs from the manifest's (the file was changed or cut short)")
  try:
    ragged = _loaded(data, entry, obs_dim)
  except ValueError as e:
    raise DemoFileError(f"{file}: not a shard of this format: {e}") from None
  try:
    return _fitted(ragged, spec)
  except ValueError as e:
    raise DemoFileError(f"{file}: {e}") from None
  except _DemonstrationError as e:
    raise DemoFileError(f"{file}: demonstration {first + e.index}: {e.error}") from None


def _loaded(data: bytes, entry: dict, obs_dim: int) -> _Ragged:
  """The arrays of a shard's bytes, of the shapes and types its manifest entry says; ValueError otherwise."""
  try:
    archive = np.load(io.BytesIO(data), allow_pickle=False)
    if not isinstance(archive, np.lib.npyio.NpzFile):
      raise ValueError("a single .npy array, not an .npz archive")
    with archive:
      arrays = {name: archive[name] for name in archive.files}
  except (OSError, EOFError, KeyError, zipfile.BadZipFile, zlib.error) as e:
    raise ValueError(str(e) or type(e).__name__) from None
  if sorted(arrays) != sorted(_ARRAYS):
    raise ValueError(f"it holds {', '.join(sorted(arrays))}; a shard holds {', '.join(_ARRAYS)}")
  num, steps = entry["demonstrations"], entry["steps"]
  _expect(arrays, "lengths", np.int32, (num,))
  _expect(arrays, "annotated", np.bool_, (num,))
  lengths = arrays["lengths"].astype(np.int64)
  if lengths.min() < 1 or lengths.sum() != steps:
    raise ValueError(f"lengths must be positive and add up to the manifest's {steps} steps")
  annotated_steps = int(lengths[arrays["annotated"]].sum())
  _expect(arrays, "observations", np.dtype(entry["observations"]), (steps + num, obs_dim))
  _expect(arrays, "actions", np.int32, (steps, None))
  _expect(arrays, "procedures", np.int32, (annotated_steps, None))
  _expect(arrays, "counters", np.int32, arrays["procedures"].shape)
  observations = arrays.pop("observations")
  if observations.dtype.kind == "f" and not np.isfinite(observations).all():
    raise ValueError("its observations hold NaN or infinity")
  return _Ragged(observations=observations, **arrays)


def _expect(arrays: dict, name: str, dtype, shape: tuple) -> None:
  array = arrays[name]
  if array.dtype != dtype or array.ndim != len(shape) or any(s not in (None, a) for s, a in zip(shape, array.shape)):
    shown = ", ".join("?" if s is None else str(s) for s in shape)
    raise ValueError(f"{name} is {array.dtype}{list(array.shape)} where {np.dtype(dtype)}[{shown}] was expected")


class _DemonstrationError(Exception):
  """A shard's demonstration (numbered from 0 in the shard) that the hierarchy refuses, and why."""

  def __init__(self, index: int, error: ValueError):
    super().__init__(index, error)
    self.index, self.error = index, error


def _fitted(ragged: _Ragged, spec: HierarchySpec) -> _Ragged:
  """ragged, its stacks [a, num_levels] even where none is annotated, if it fits spec: its action factors and
  stack levels (ValueError), its actions in range and its stacks by the call-stack rules (_DemonstrationError
  for the first demonstration that breaks either, as the JSON reader's first bad line)."""
  sizes, depth = spec.action_sizes, spec.num_levels
  if ragged.actions.shape[1] != len(sizes):
    raise ValueError(f"actions have {ragged.actions.shape[1]} factors where the hierarchy's have {len(sizes)} (a "
                     "file of another hierarchy or environment)")
  if len(ragged.procedures) and ragged.procedures.shape[1] != depth:
    raise ValueError(f"stacks have {ragged.procedures.shape[1]} levels where the hierarchy has {depth}")
  if not len(ragged.procedures):
    ragged = ragged._replace(procedures=np.zeros((0, depth), np.int32), counters=np.zeros((0, depth), np.int32))
  refusals = [r for r in (_action_refusal(ragged, sizes), _stack_refusal(ragged, spec)) if r]
  if refusals:
    raise min(refusals, key=lambda r: r.index)  # an action before a stack in one demonstration, as the JSON reader
  return ragged


def _action_refusal(ragged: _Ragged, sizes: tuple[int, ...]) -> _DemonstrationError | None:
  """The first demonstration with an action outside its factor's range, or None."""
  bad = np.argwhere((ragged.actions < 0) | (ragged.actions >= np.array(sizes)))
  if not bad.size:
    return None
  row, factor = bad[0]
  ends = np.cumsum(ragged.lengths, dtype=np.int64)
  demo = int(np.searchsorted(ends, row, side="right"))
  t = int(row - (ends[demo] - ragged.lengths[demo]))
  return _DemonstrationError(demo, action_error(t, int(factor), int(ragged.actions[row, factor]), sizes))


def _stack_refusal(ragged: _Ragged, spec: HierarchySpec) -> _DemonstrationError | None:
  """The first annotated demonstration whose stack `check_stack` refuses, or None; only the suspects that
  _stack_suspects finds at array speed are checked one by one."""
  lengths = ragged.lengths[ragged.annotated].astype(np.int64)
  ends = np.cumsum(lengths)
  numbers = np.flatnonzero(ragged.annotated)
  for i in _stack_suspects(ragged.procedures, ragged.counters, lengths, spec):
    rows = slice(ends[i] - lengths[i], ends[i])
    try:
      check_stack(ragged.procedures[rows], ragged.counters[rows], spec)
    except ValueError as e:
      return _DemonstrationError(int(numbers[i]), e)
  return None


def _stack_suspects(procs: np.ndarray, taus: np.ndarray, lengths: np.ndarray, spec: HierarchySpec) -> np.ndarray:
  """Which of the stacks (lengths [a] of them, [Σ lengths, d] one after another) may break the rules
  `check_stack` holds them to: every one it refuses, and perhaps a few it passes."""
  t = (np.arange(len(procs)) - np.repeat(np.cumsum(lengths) - lengths, lengths))[:, None]  # step in its own
  known = (procs != UNKNOWN) & (taus != UNKNOWN)
  sizes = np.array([spec.num_procs(level) for level in range(spec.num_levels)])
  bad = ((procs != UNKNOWN) != (taus != UNKNOWN)) | (taus > t) | (known & (
      (procs < 0) | (procs >= sizes) | (taus < 0) | ((t == 0) & (taus != 0))))
  bad = bad.any(axis=1)
  whole = known.all(axis=1)
  follows = (t[1:, 0] > 0) & whole[1:] & whole[:-1]
  bad[1:] |= follows & ~_resumes(procs[:-1], taus[:-1], procs[1:], taus[1:])
  return np.unique(np.repeat(np.arange(len(lengths)), lengths)[bad])


def _resumes(prev_procs, prev_taus, procs, taus) -> np.ndarray:
  """[S] whether each stack [S, d] follows the one before it by one action (`demos._stack_error`'s rule): one
  level j resumes (τ + 1), the levels above keep their frames and every level below starts afresh (τ = 0)."""
  ones = np.ones((len(procs), 1), bool)
  kept = (procs == prev_procs) & (taus == prev_taus)
  above = np.logical_and.accumulate(np.concatenate([ones, kept[:, :-1]], axis=1), axis=1)
  fresh = np.concatenate([taus[:, 1:] == 0, ones], axis=1)
  below = np.logical_and.accumulate(fresh[:, ::-1], axis=1)[:, ::-1]
  return (above & (procs == prev_procs) & (taus == prev_taus + 1) & below).any(axis=1)


def _padded(ragged: _Ragged, depth: int) -> Demonstration:
  """ragged's demonstrations as one batch [n, ...] padded to its longest (zeros, and UNKNOWN in the stacks):
  the JSON reader's batch of the same demonstrations."""
  lengths = ragged.lengths.astype(np.int64)
  num, width = len(lengths), int(lengths.max())
  starts = np.cumsum(lengths) - lengths
  demo = np.repeat(np.arange(num), lengths)
  t = np.arange(len(demo)) - np.repeat(starts, lengths)
  observations = np.zeros((num, width + 1, ragged.observations.shape[1]), ragged.observations.dtype)
  rows = np.arange(len(ragged.observations)) - np.repeat(starts + np.arange(num), lengths + 1)
  observations[np.repeat(np.arange(num), lengths + 1), rows] = ragged.observations
  actions = np.zeros((num, width, ragged.actions.shape[1]), np.int32)
  actions[demo, t] = ragged.actions
  procs, taus = (np.full((num, width, depth), UNKNOWN, np.int32) for _ in range(2))
  annotated = ragged.annotated[demo]
  procs[demo[annotated], t[annotated]] = ragged.procedures
  taus[demo[annotated], t[annotated]] = ragged.counters
  return Demonstration(observations, actions, procs, taus, ragged.lengths.astype(np.int32),
                       ragged.annotated.astype(bool))
