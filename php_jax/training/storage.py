"""Arrays on disk as signed Orbax checkpoints: the storage under saved models (`checkpoint`) and training
state (`resume`).

Arrays are named by their pytree path ("levels/0/operation/kernels/0") and saved as one Orbax checkpoint in a
directory (Orbax writes it in a temporary directory renamed into place once complete); the JSON that describes
it records the sha256 of every file, and its own (`signed`). Before Orbax reads a checkpoint, its files are
checked against those sums (`restore_arrays`), so that a file edited, cut short or swapped for another run's is
refused in one line. Arrays are restored as they were saved (no target, so Orbax neither casts nor reshapes),
then checked against the model (`restore_named`): every name present, every shape and dtype as expected.
"""
from __future__ import annotations

import contextlib
import glob
import hashlib
import json
import logging
import os
import re
import shutil
import sys
import time
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np

TEMPORARY = "*.orbax-checkpoint-tmp*"  # what a save cut off leaves


class CheckpointError(ValueError):
  """A saved file that cannot be used: missing, corrupt, or not matching the model; the message names it."""


def _path_name(path) -> str:
  """A pytree path's name: its keys, indices and attribute names joined by "/"."""
  def key_name(key) -> str:
    for attribute in ("key", "idx", "name"):  # DictKey, SequenceKey, GetAttrKey
      if hasattr(key, attribute):
        return str(getattr(key, attribute))
    return str(key)
  return "/".join(map(key_name, path))


def named_arrays(tree) -> dict[str, np.ndarray]:
  """{path name ("levels/0/operation/kernels/0"): host array} of a pytree's leaves."""
  return {_path_name(path): np.asarray(leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _nested(named: dict[str, np.ndarray]) -> dict:
  """The nested dicts of named_arrays' names (what is saved; a restore without target returns them)."""
  nested: dict = {}
  for name, value in named.items():
    *parents, leaf = name.split("/")
    node = nested
    for parent in parents:
      node = node.setdefault(parent, {})
    node[leaf] = value
  return nested


def part(named: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
  """The arrays named prefix/..., named by the rest."""
  return {name[len(prefix) + 1:]: value for name, value in named.items() if name.startswith(prefix + "/")}


def restore_named(template, named: dict, source: str):
  """The pytree shaped like template with the arrays of `named`; raises CheckpointError naming `source` and
  the first missing, unexpected or mis-shaped array."""
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  names = [_path_name(path) for path, _ in leaves]
  unexpected = sorted(set(named) - set(names))
  if unexpected:
    raise CheckpointError(f"{source}: unexpected array {unexpected[0]} (saved with another architecture?)")
  restored = []
  for name, (_, leaf) in zip(names, leaves):
    if name not in named:
      raise CheckpointError(f"{source}: array {name} is missing (saved with another architecture?)")
    value = np.asarray(named[name])
    dtype = np.dtype(leaf.dtype) if hasattr(leaf, "dtype") else np.asarray(leaf).dtype  # arrays or their shapes
    if value.shape != np.shape(leaf) or value.dtype != dtype:
      raise CheckpointError(f"{source}: array {name} is {value.dtype}{list(value.shape)}; the model needs "
                            f"{dtype}{list(np.shape(leaf))}")
    restored.append(jnp.asarray(value))
  return jax.tree_util.tree_unflatten(treedef, restored)


def _sha256(data: bytes) -> str:
  return hashlib.sha256(data).hexdigest()


def signed(described: dict) -> dict:
  """described with "sha256": the checksum of its other entries."""
  return {**described, "sha256": _sha256(json.dumps(described, sort_keys=True).encode())}


def check_signed(path: str, described: dict) -> None:
  if described.get("sha256") != signed({k: v for k, v in described.items() if k != "sha256"})["sha256"]:
    raise CheckpointError(f"{path}: edited or corrupt (checksum); train it again")


def _not_from_orbax(record: logging.LogRecord) -> bool:
  return f"{os.sep}orbax{os.sep}" not in record.pathname


def _without_closed_loop_reports(hook):
  """sys.unraisablehook less the RuntimeError("Event loop is closed") that TensorStore's callbacks raise when
  they complete after a failed Orbax save or read has closed its event loop."""
  def unraisable(report):
    if not (isinstance(report.exc_value, RuntimeError) and str(report.exc_value) == "Event loop is closed"):
      hook(report)
  unraisable.php_jax_wraps = hook
  return unraisable


@contextlib.contextmanager
def _orbax_quiet():
  """Orbax's own log records (absl's logger) held back meanwhile, so that a failed save or read reaches the
  caller as the exception it raises, in one line, not also as Orbax's tracebacks. After a failure,
  TensorStore's late callbacks stay unreported."""
  logger = logging.getLogger("absl")
  logger.addFilter(_not_from_orbax)
  before = sys.unraisablehook
  if not hasattr(before, "php_jax_wraps"):
    sys.unraisablehook = _without_closed_loop_reports(before)
  try:
    yield
    sys.unraisablehook = before  # after a failure the filter stays: TensorStore's callbacks come late
  finally:
    logger.removeFilter(_not_from_orbax)


def _orbax_checkpoint(directory: str, tree: dict | None = None) -> dict | None:
  """Saves tree as the Orbax checkpoint at directory (replacing one there), or with tree None restores the one
  there as it was saved. Synchronous, with Orbax's standard handler, in this process alone: of several
  processes (jax.distributed) only the first writes, and each reads by itself. Orbax is imported here, when a
  command first saves or reads, not when it starts."""
  import orbax.checkpoint as ocp

  index = jax.process_index()
  alone = ocp.options.MultiprocessingOptions(primary_host=index, active_processes={index},
                                             barrier_sync_key_prefix=f"php_jax_process_{index}")
  checkpointer = ocp.Checkpointer(ocp.StandardCheckpointHandler(multiprocessing_options=alone),
                                  multiprocessing_options=alone)
  if tree is None:
    return checkpointer.restore(os.path.abspath(directory))
  checkpointer.save(os.path.abspath(directory), args=ocp.args.StandardSave(tree), force=True)
  return None


def _files(directory: str) -> dict[str, str]:
  """{path relative to directory: sha256} of every file under directory."""
  found = {}
  for root, _, names in os.walk(directory):
    for name in names:
      with open(os.path.join(root, name), "rb") as f:
        found[os.path.relpath(os.path.join(root, name), directory)] = _sha256(f.read())
  return found


def save_arrays(directory: str, named: dict[str, np.ndarray]) -> dict[str, str]:
  """An Orbax checkpoint of the named arrays at directory (replacing one there); returns its files' sha256.
  If the save fails, its temporary directory is removed and a failed write (TensorStore's ValueError naming
  an os_error_code) raised as the OSError it was."""
  try:
    with _orbax_quiet():
      _orbax_checkpoint(directory, _nested(named))
  except BaseException as e:
    _remove_temporary(directory)
    code = re.search(r"os_error_code='(\d+)'", str(e))
    if code and not isinstance(e, OSError):
      raise OSError(int(code[1]), os.strerror(int(code[1])), directory) from None
    raise
  return _files(directory)


def _remove_temporary(directory: str) -> None:
  """Removes the temporary directory of a failed save to directory, waiting out TensorStore's writes still in
  flight, which would make it again: until it has stayed absent for 0.1 s (for at most 2 s)."""
  deadline, absent_since = time.monotonic() + 2.0, None
  while time.monotonic() < deadline:
    leftovers = glob.glob(glob.escape(directory) + TEMPORARY[1:])
    for leftover in leftovers:
      shutil.rmtree(leftover, ignore_errors=True)
    now = time.monotonic()
    absent_since = None if leftovers else absent_since or now
    if absent_since and now - absent_since >= 0.1:
      return
    time.sleep(0.01)


def restore_arrays(directory: str, files: Any, source: str) -> dict[str, np.ndarray]:
  """The named arrays of the Orbax checkpoint at directory, once its files are those `files` ({path:
  sha256}, as save_arrays returned, from `source`) lists; CheckpointError naming the first that is not."""
  found = _files(directory) if os.path.isdir(directory) else {}
  if not isinstance(files, dict) or not files:
    raise CheckpointError(f"{source}: no list of the files of {directory}")
  for name in sorted(set(files) | set(found)):
    if files.get(name) != found.get(name):
      what = (f"is missing (listed in {source})" if name not in found else f"is not listed in {source}"
              if name not in files else f"does not match its checksum in {source}")
      raise CheckpointError(f"{os.path.join(directory, name)} {what}: edited, corrupt or from another run; "
                            "train it again")
  try:
    with _orbax_quiet():
      return named_arrays(_orbax_checkpoint(directory))
  except (ValueError, OSError) as e:  # files as saved, so only a version of Orbax that cannot read them
    raise CheckpointError(f"{directory}: cannot be read ({str(e)[:200]})") from None


def read_json(path: str) -> Any:
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (ValueError, UnicodeDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt or truncated JSON ({e})") from None


def remove_saved(path: str) -> None:
  """Deletes a checkpoint, a model's parameters or a file at path, if there is one."""
  if os.path.isdir(path) and not os.path.islink(path):
    shutil.rmtree(path)
  elif os.path.lexists(path):
    os.remove(path)
