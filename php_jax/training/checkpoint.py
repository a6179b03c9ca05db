"""Saved models and training state: arrays in Orbax checkpoints (`orbax.checkpoint`), described by JSON.

A model is workdir/model.json (task, architecture, and the sha256 of every file of the parameters) and
workdir/model/ (the parameters, an Orbax checkpoint). A training checkpoint is the directory workdir/checkpoint/:
state.json (per run trained: the level, the settings it was made with, the report so far, the optimizer's
progress; the step and its files' sha256) and the step it names, an Orbax checkpoint of the arrays (per run:
the hierarchy's parameters, the optimizer state of the level in progress, the decoded views of finished levels).
A save writes the new step (Orbax writes it in a temporary directory renamed into place once complete), then
state.json (a temporary file renamed into place), then removes the older step: a reader sees the old
checkpoint or the new one, never part of one, and a save cut off leaves only what the next save removes.

Before Orbax reads a checkpoint, its files are checked against the sha256 the JSON records (and the JSON
against its own), so that a file edited, cut short or swapped for another run's is refused in one line. Arrays
are named by their pytree path ("levels/0/operation/kernels/0") and restored as they were saved (no target, so
Orbax neither casts nor reshapes), then checked against the model: every name present, every shape and dtype as
expected.
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
import optax
from flax import nnx

from php_jax import fitting
from php_jax.data.files import WRITING, write_atomically
from php_jax.envs import tasks
from php_jax.flat_lstm import FlatLSTMPolicy
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy

MODEL_DIR, ARCHITECTURE_FILE, TRAINING_DIR = "model", "model.json", "checkpoint"
MODEL_FILES = (ARCHITECTURE_FILE, MODEL_DIR)  # what load_policy reads
OLDER_FILES = ("model.msgpack", "checkpoint.msgpack", "seeds_checkpoint.msgpack")  # php_jax before Orbax
TEMPORARY = "*.orbax-checkpoint-tmp*"  # what a save cut off leaves
STATE_FILE = "state.json"  # in a training checkpoint: the step to read and what it holds

MAX_CAPACITY = 4096  # counters per level a saved model may claim (a hierarchy file's bound too)
MAX_SIZE = 1 << 20  # observation size, action factor size and procedures per level a saved model may claim


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


def _part(named: dict[str, np.ndarray], prefix: str) -> dict[str, np.ndarray]:
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


def _signed(described: dict) -> dict:
  """described with "sha256": the checksum of its other entries."""
  return {**described, "sha256": _sha256(json.dumps(described, sort_keys=True).encode())}


def _check_signed(path: str, described: dict) -> None:
  if described.get("sha256") != _signed({k: v for k, v in described.items() if k != "sha256"})["sha256"]:
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


def _save_arrays(directory: str, named: dict[str, np.ndarray]) -> dict[str, str]:
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


def _restore_arrays(directory: str, files: Any, source: str) -> dict[str, np.ndarray]:
  """The named arrays of the Orbax checkpoint at directory, once its files are those `files` ({path:
  sha256}, as _save_arrays returned, from `source`) lists; CheckpointError naming the first that is not."""
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


def _read_json(path: str) -> Any:
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (ValueError, UnicodeDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt or truncated JSON ({e})") from None


def _save(workdir: str, model, architecture: dict) -> None:
  """workdir/model/ (the parameters), then model.json listing its files' sha256 (so a model.json never
  describes other parameters, even if a save is cut off between the two)."""
  if jax.process_index() != 0:  # of several processes (jax.distributed), the first writes: the others agree
    return
  with WRITING:  # an interrupt waits for model.json too
    files = _save_arrays(os.path.join(workdir, MODEL_DIR), named_arrays(nnx.state(model, nnx.Param)))
    write_atomically(os.path.join(workdir, ARCHITECTURE_FILE),
                     json.dumps(_signed({**architecture, "files": files}), indent=1).encode())


def _spec_json(spec: HierarchySpec) -> dict:
  observes = None if spec.observes is None else [
      None if level is None else [None if entries is None else list(entries) for entries in level]
      for level in spec.observes]
  return {"name": spec.name, "levels": [list(level) for level in spec.levels],
          "action_sizes": list(spec.action_sizes), "obs_dim": spec.obs_dim,
          **({"observes": observes} if observes is not None else {})}


def save_hierarchy(workdir: str, task_name: str, hierarchy: PHPHierarchy, hidden,
                   capacity: list[int] | None = None) -> None:
  """Writes workdir/model.json (task, hierarchy spec, architecture and, when given, the counter capacity per
  level it was trained with, root first) and workdir/model.msgpack (parameters)."""
  _save(workdir, hierarchy, {"task": task_name, "kind": "php", "spec": _spec_json(hierarchy.spec),
                             "hidden": list(hidden),
                             "tau_in_termination": [level.tau_in_termination for level in hierarchy.levels],
                             "tau_limit": [level.tau_limit for level in hierarchy.levels],
                             "allowed_ops": [level.allowed_ops for level in hierarchy.levels],
                             **({"capacity": list(capacity)} if capacity else {})})


def save_flat_lstm(workdir: str, task_name: str, policy: FlatLSTMPolicy, spec: HierarchySpec) -> None:
  """The flat LSTM baseline, in the same two files."""
  _save(workdir, policy, {"task": task_name, "kind": "flat_lstm", "spec": _spec_json(spec),
                          "hidden": policy.hidden})


def _saved_spec(path: str, architecture: dict) -> HierarchySpec:
  """The spec model.json records (or, for a model saved without one, its registered task's)."""
  if "spec" not in architecture:
    return tasks.get(architecture["task"]).spec
  spec = architecture["spec"]
  try:
    observes = spec.get("observes")
    if observes is not None:
      observes = tuple(None if level is None else tuple(None if entries is None else tuple(entries)
                                                        for entries in level) for level in observes)
    saved = HierarchySpec(str(spec["name"]), tuple(tuple(map(str, level)) for level in spec["levels"]),
                          tuple(int(n) for n in spec["action_sizes"]), int(spec["obs_dim"]), observes=observes)
  except (AttributeError, TypeError, KeyError, ValueError):
    raise CheckpointError(f"{path}: malformed hierarchy spec {str(spec)[:200]}") from None
  sizes = (saved.obs_dim, *saved.action_sizes, *map(len, saved.levels))
  if not (saved.levels and isinstance(spec["levels"], list) and saved.action_sizes
          and all(1 <= n <= MAX_SIZE for n in sizes)):
    raise CheckpointError(f"{path}: malformed hierarchy spec (sizes must be in 1..{MAX_SIZE}) {str(spec)[:200]}")
  return saved


def saved_capacity(workdir: str) -> tuple[int, ...] | None:
  """The counter capacity per level (root first) a saved PHP hierarchy was trained with, if recorded."""
  path = os.path.join(workdir, ARCHITECTURE_FILE)
  architecture = _read_json(path)
  capacity = architecture.get("capacity")
  if not capacity:
    return None
  levels = (architecture.get("spec") or {}).get("levels") if isinstance(architecture.get("spec"), dict) else None
  if not (isinstance(capacity, list) and all(isinstance(c, int) and not isinstance(c, bool) and 1 <= c <= MAX_CAPACITY
                                             for c in capacity)
          and (levels is None or len(capacity) == len(levels))):
    raise CheckpointError(f"{path}: \"capacity\" must give one integer in 1..{MAX_CAPACITY} per level; got "
                          f"{str(capacity)[:80]}")
  return tuple(capacity)


def _architecture(path: str, architecture) -> tuple:
  """(task name, kind, hidden, (tau_in_termination, tau_limit)) from model.json, checked."""
  if not isinstance(architecture, dict) or not isinstance(architecture.get("task"), str):
    raise CheckpointError(f"{path}: not a model description (needs a \"task\")")
  kind = architecture.get("kind", "php")
  hidden = architecture.get("hidden")
  if kind == "flat_lstm" and isinstance(hidden, int) and hidden > 0:
    return architecture["task"], kind, hidden, None
  tau = architecture.get("tau_in_termination")
  limit = architecture.get("tau_limit", [None] * len(tau) if isinstance(tau, list) else None)
  if (kind == "php" and isinstance(hidden, list) and all(isinstance(h, int) and h > 0 for h in hidden)
      and isinstance(tau, list) and all(isinstance(t, bool) for t in tau) and isinstance(limit, list)
      and len(limit) == len(tau) and all(v is None or (isinstance(v, int) and v >= 0) for v in limit)):
    return architecture["task"], kind, tuple(hidden), (tuple(tau), tuple(limit))
  raise CheckpointError(f"{path}: malformed model description {architecture}")


def _saved_allowed_ops(path: str, architecture: dict, spec: HierarchySpec) -> tuple | None:
  """The call graph model.json records (None, every operation allowed, for a model saved without one)."""
  graph = architecture.get("allowed_ops")
  if graph is None:
    return None

  def fits(g, level: int) -> bool:
    return (isinstance(g, list) and len(g) == spec.num_procs(level)
            and all(isinstance(row, list) and len(row) == sum(spec.op_sizes(level))
                    and all(isinstance(c, bool) for c in row) for row in g))

  if isinstance(graph, list) and len(graph) == spec.num_levels and all(g is None or fits(g, i)
                                                                       for i, g in enumerate(graph)):
    return tuple(None if g is None else tuple(map(tuple, g)) for g in graph)
  raise CheckpointError(f"{path}: malformed allowed_ops {graph} (per level, root first: null or "
                        f"[procedure][operation factor value] booleans)")


def load_policy(workdir: str) -> tuple[str, PHPHierarchy | FlatLSTMPolicy]:
  """(task name, model) saved by save_hierarchy or save_flat_lstm. Raises FileNotFoundError if workdir holds
  no model, CheckpointError if its files are corrupt or disagree with each other."""
  arch_path, model_path = (os.path.join(workdir, f) for f in (ARCHITECTURE_FILE, MODEL_DIR))
  if os.path.isfile(arch_path) and not os.path.isdir(model_path) and os.path.isfile(model_path + ".msgpack"):
    raise CheckpointError(f"{model_path}.msgpack was saved by an older php_jax; train the model again")
  if not (os.path.isfile(arch_path) and os.path.isdir(model_path)):
    raise FileNotFoundError(f"no trained model in {workdir!r} (expected {ARCHITECTURE_FILE} and {MODEL_DIR}/)")
  architecture = _read_json(arch_path)
  task_name, kind, hidden, tau = _architecture(arch_path, architecture)
  _check_signed(arch_path, architecture)
  named = _restore_arrays(model_path, architecture.get("files"), arch_path)
  spec = _saved_spec(arch_path, architecture)
  if kind == "flat_lstm":
    def build():
      return FlatLSTMPolicy(spec.obs_dim, spec.action_sizes, hidden, rngs=nnx.Rngs(0))
  else:
    tau_in_termination, tau_limit = tau
    if len(tau_in_termination) != spec.num_levels:
      raise CheckpointError(f"{arch_path}: tau_in_termination has {len(tau_in_termination)} entries; {task_name} "
                            f"has {spec.num_levels} levels")
    allowed_ops = _saved_allowed_ops(arch_path, architecture, spec)

    def build():
      return PHPHierarchy(spec, hidden=hidden, tau_in_termination=tau_in_termination, tau_limit=tau_limit,
                          allowed_ops=allowed_ops, rngs=nnx.Rngs(0))
  model = nnx.eval_shape(build)  # its shapes only: every parameter comes from the file (and no state but them)
  nnx.update(model, restore_named(nnx.state(model, nnx.Param), named, model_path))
  return task_name, model


def write_training(path: str, hierarchy: PHPHierarchy, meta: dict, progress: fitting.Progress | None,
                   decoded: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
  """A training checkpoint at path (a directory): the hierarchy's parameters, the in-progress level's
  optimizer state (progress), the decoded views of finished levels, and meta (JSON: the level, the settings,
  the report so far)."""
  write_training_seeds(path, [(hierarchy, meta, progress, decoded)])


def write_training_seeds(path: str, states: list[tuple]) -> None:
  """One checkpoint holding several seeds' training states, each (hierarchy, meta, progress, decoded) as
  write_training takes them (`train.train_seeds`): saved at once, so the seeds never disagree on where they
  stand. Of several processes (jax.distributed), only the first writes."""
  if jax.process_index() != 0:
    return
  named, metas = {}, []
  for s, (hierarchy, meta, progress, decoded) in enumerate(states):
    metas.append({**meta, "progress": None if progress is None else {
        "iteration": progress.iteration, "best_iteration": progress.best_iteration,
        "best_score": progress.best_score, "losses": progress.losses}})
    named.update({f"{s}/hierarchy/{k}": v for k, v in named_arrays(nnx.state(hierarchy, nnx.Param)).items()})
    if progress is not None:
      named.update({f"{s}/progress/{k}": v for k, v in
                    named_arrays((progress.params, progress.opt_state, progress.best_params)).items()})
    for level, (procedures, counters) in decoded.items():
      named.update({f"{s}/decoded/{level}/procedures": np.asarray(procedures),
                    f"{s}/decoded/{level}/counters": np.asarray(counters)})
  os.makedirs(path, exist_ok=True)
  step = str(max((int(name) for name in os.listdir(path) if name.isdigit()), default=-1) + 1)
  metas = json.loads(json.dumps(metas))  # as state.json reads back (its keys strings), so that its checksum holds
  with WRITING:  # an interrupt waits until the old step is gone too
    files = _save_arrays(os.path.join(path, step), named)
    try:
      write_atomically(os.path.join(path, STATE_FILE), json.dumps(_signed({"states": metas, "step": int(step),
                                                                              "files": files})).encode())
    except BaseException:  # the step state.json would have named is no checkpoint's
      remove_saved(os.path.join(path, step))
      raise
    for name in os.listdir(path):  # the step before, or what a save cut off left
      if name not in (step, STATE_FILE):
        remove_saved(os.path.join(path, name))


def read_training(path: str | None) -> tuple[dict, dict] | None:
  """(meta, arrays) from a training checkpoint, or None if there is none. Raises CheckpointError if it is
  corrupt, or holds several seeds' states."""
  states = read_training_seeds(path)
  if states is not None and len(states) != 1:
    raise CheckpointError(f"{path} holds {len(states)} seeds' training states, not one run's")
  return states and states[0]


def read_training_seeds(path: str | None) -> list[tuple[dict, dict]] | None:
  """Each seed's (meta, arrays) from a checkpoint write_training_seeds (or write_training) saved, or None if
  there is none (or only a save cut off). Raises CheckpointError if it is corrupt or not such a checkpoint."""
  if not path or not os.path.exists(path):
    return None
  if not os.path.isdir(path):
    raise CheckpointError(f"{path}: not a training checkpoint (a file, not a directory)")
  state_path = os.path.join(path, STATE_FILE)
  if not os.path.isfile(state_path):  # the first save was cut off
    return None
  state = _read_json(state_path)
  if not (isinstance(state, dict) and isinstance(state.get("states"), list) and state["states"]
          and all(isinstance(m, dict) and "level" in m and "progress" in m for m in state["states"])):
    raise CheckpointError(f"{state_path}: not a training checkpoint's state")
  _check_signed(state_path, state)
  named = _restore_arrays(os.path.join(path, str(state.get("step"))), state.get("files"), state_path)
  return [(meta, _part(named, str(s))) for s, meta in enumerate(state["states"])]


def restore_hierarchy(path: str, saved: tuple[dict, dict], hierarchy: PHPHierarchy) -> None:
  """Loads the checkpoint's parameters into hierarchy."""
  nnx.update(hierarchy, restore_named(nnx.state(hierarchy, nnx.Param), _part(saved[1], "hierarchy"), path))


def restore_progress(path: str, saved: tuple[dict, dict], model: nnx.Module) -> fitting.Progress:
  """The saved in-progress level's Progress, shaped like a fresh Adam optimizer for `model`."""
  meta, named = saved
  params = nnx.state(model, nnx.Param)
  restored = restore_named((params, optax.adam(0.0).init(params), params), _part(named, "progress"), path)
  p = meta["progress"]
  return fitting.Progress(p["iteration"], *restored, p["best_iteration"], p["best_score"],
                          [list(x) for x in p["losses"]])


def decoded_views(saved: tuple[dict, dict]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """The (procedures, counters) [B, T] per finished level > 0: each level's view of every demonstration,
  annotated where strong and decoded where weak."""
  decoded = _part(saved[1], "decoded")
  levels = sorted({int(name.split("/")[0]) for name in decoded})
  return {level: (decoded[f"{level}/procedures"], decoded[f"{level}/counters"]) for level in levels}


def read_decoded(path: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """decoded_views of the training checkpoint at path. Raises CheckpointError if it is corrupt."""
  saved = read_training(path)
  if saved is None:
    raise FileNotFoundError(f"no training checkpoint at {path}")
  try:
    return decoded_views(saved)
  except (KeyError, ValueError) as e:
    raise CheckpointError(f"{path}: no decoded views ({e!r})") from None


def remove_saved(path: str) -> None:
  """Deletes a checkpoint, a model's parameters or a file at path, if there is one."""
  if os.path.isdir(path) and not os.path.islink(path):
    shutil.rmtree(path)
  elif os.path.lexists(path):
    os.remove(path)
