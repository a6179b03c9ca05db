"""Saved models and training state, in one format: arrays in a msgpack map keyed by their pytree path
(`jax.tree_util.keystr`), checked against the model's structure on load (every name present, every shape and
dtype as expected), beside JSON metadata. Files are written atomically (a temporary file renamed into
place), so a workdir never holds half a model or half a checkpoint.

A model is workdir/model.json (task and architecture) and workdir/model.msgpack (parameters). A training
checkpoint is one msgpack file: the hierarchy's parameters, the optimizer state of the level in progress,
the decoded views of finished levels, and its metadata (the settings it was made with, the report so far).
"""
from __future__ import annotations

import hashlib
import json
import os
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, serialization

from php_jax import fitting
from php_jax.data.files import write_atomically
from php_jax.envs import tasks
from php_jax.flat_lstm import FlatLSTMPolicy
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy

MODEL_FILE, ARCHITECTURE_FILE, TRAINING_FILE = "model.msgpack", "model.json", "checkpoint.msgpack"
MODEL_FILES = (ARCHITECTURE_FILE, MODEL_FILE)  # what load_policy reads


MAX_CAPACITY = 4096  # counters per level a saved model may claim (a hierarchy file's bound too)
MAX_SIZE = 1 << 20  # observation size, action factor size and procedures per level a saved model may claim


class CheckpointError(ValueError):
  """A saved file that cannot be used: missing, corrupt, or not matching the model; the message names it."""


def named_arrays(tree) -> dict[str, np.ndarray]:
  """{path name: array} of a pytree's leaves."""
  return {jax.tree_util.keystr(path): np.asarray(leaf) for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def restore_named(template, named: dict, source: str):
  """The pytree shaped like template with the arrays of `named`; raises CheckpointError naming `source` and
  the first missing, unexpected or mis-shaped array."""
  leaves, treedef = jax.tree_util.tree_flatten_with_path(template)
  names = [jax.tree_util.keystr(path) for path, _ in leaves]
  if not isinstance(named, dict):
    raise CheckpointError(f"{source}: not a map of named arrays")
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


def _unpack(data: bytes, path: str) -> Any:
  try:
    return serialization.msgpack_restore(data)
  except (ValueError, TypeError, KeyError, IndexError) as e:
    raise CheckpointError(f"{path}: corrupt or truncated ({e})") from None


def _read_json(path: str) -> Any:
  try:
    with open(path, encoding="utf-8") as f:
      return json.load(f)
  except (ValueError, UnicodeDecodeError) as e:
    raise CheckpointError(f"{path}: corrupt or truncated JSON ({e})") from None


def _digest(data: bytes) -> str:
  return hashlib.sha256(data).hexdigest()


def _model_digest(params: bytes, architecture: dict) -> str:
  """The checksum model.json carries: of the parameters and of every other entry of model.json, so that
  neither file can be edited, cut short or swapped for another run's unnoticed."""
  described = json.dumps({k: v for k, v in architecture.items() if k != "sha256"}, sort_keys=True)
  return _digest(params + described.encode())


def _save(workdir: str, model, architecture: dict) -> None:
  """model.msgpack, then model.json with the checksum of both (so a model.json never describes other
  parameters, even if a write is cut off between the two)."""
  params = serialization.msgpack_serialize(named_arrays(nnx.state(model, nnx.Param)))
  write_atomically(os.path.join(workdir, MODEL_FILE), params)
  write_atomically(os.path.join(workdir, ARCHITECTURE_FILE),
                   json.dumps({**architecture, "sha256": _model_digest(params, architecture)}, indent=1).encode())


def _spec_json(spec: HierarchySpec) -> dict:
  return {"name": spec.name, "levels": [list(level) for level in spec.levels],
          "action_sizes": list(spec.action_sizes), "obs_dim": spec.obs_dim}


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
    saved = HierarchySpec(str(spec["name"]), tuple(tuple(map(str, level)) for level in spec["levels"]),
                          tuple(int(n) for n in spec["action_sizes"]), int(spec["obs_dim"]))
  except (TypeError, KeyError, ValueError):
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
  arch_path, model_path = (os.path.join(workdir, f) for f in (ARCHITECTURE_FILE, MODEL_FILE))
  if not (os.path.isfile(arch_path) and os.path.isfile(model_path)):
    raise FileNotFoundError(f"no trained model in {workdir!r} (expected {ARCHITECTURE_FILE} and {MODEL_FILE})")
  architecture = _read_json(arch_path)
  task_name, kind, hidden, tau = _architecture(arch_path, architecture)
  with open(model_path, "rb") as f:
    params = f.read()
  if architecture.get("sha256") != _model_digest(params, architecture):
    raise CheckpointError(f"{model_path} does not match {arch_path} (checksum): edited, corrupt, from another "
                          "run, or saved by an older php_jax (then train it again)")
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
  nnx.update(model, restore_named(nnx.state(model, nnx.Param), _unpack(params, model_path), model_path))
  return task_name, model


def write_training(path: str, hierarchy: PHPHierarchy, meta: dict, progress: fitting.Progress | None,
                   decoded: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
  """One file: the hierarchy's parameters, the in-progress level's optimizer state (progress), the decoded
  views of finished levels, and meta (JSON: the level, the settings, the report so far)."""
  write_atomically(path, _training_bytes(hierarchy, meta, progress, decoded))


def write_training_seeds(path: str, states: list[tuple]) -> None:
  """One file holding several seeds' training states, each (hierarchy, meta, progress, decoded) as
  write_training takes them (`train.train_seeds`): written at once, so the seeds never disagree on where they
  stand."""
  write_atomically(path, serialization.msgpack_serialize({"seeds": [_training_bytes(*state) for state in states]}))


def _training_bytes(hierarchy: PHPHierarchy, meta: dict, progress: fitting.Progress | None,
                    decoded: dict[int, tuple[np.ndarray, np.ndarray]]) -> bytes:
  meta = {**meta, "progress": None if progress is None else {
      "iteration": progress.iteration, "best_iteration": progress.best_iteration,
      "best_score": progress.best_score, "losses": progress.losses}}
  arrays = serialization.msgpack_serialize({
      "hierarchy": named_arrays(nnx.state(hierarchy, nnx.Param)),
      "progress": {} if progress is None else named_arrays((progress.params, progress.opt_state,
                                                             progress.best_params)),
      "decoded": {str(k): {"procedures": v[0], "counters": v[1]} for k, v in decoded.items()}})
  return serialization.msgpack_serialize({"arrays": arrays, "sha256": _digest(arrays), "meta": json.dumps(meta)})


def read_training(path: str | None) -> tuple[dict, dict] | None:
  """(meta, arrays) from a training checkpoint, or None if there is none. Raises CheckpointError if the file
  is corrupt."""
  if not path or not os.path.isfile(path):
    return None
  with open(path, "rb") as f:
    return _parse_training(f.read(), path)


def read_training_seeds(path: str | None) -> list[tuple[dict, dict]] | None:
  """Each seed's (meta, arrays) from a file write_training_seeds wrote, or None if there is none. Raises
  CheckpointError if the file is corrupt or not such a file."""
  if not path or not os.path.isfile(path):
    return None
  with open(path, "rb") as f:
    seeds = _unpack(f.read(), path)
  if not (isinstance(seeds, dict) and isinstance(seeds.get("seeds"), list)
          and all(isinstance(state, bytes) for state in seeds["seeds"])):
    raise CheckpointError(f"{path}: not a checkpoint of several seeds")
  return [_parse_training(state, path) for state in seeds["seeds"]]


def _parse_training(data: bytes, path: str) -> tuple[dict, dict]:
  state = _unpack(data, path)
  try:
    meta, arrays, digest = json.loads(state["meta"]), state["arrays"], state["sha256"]
  except (TypeError, KeyError, ValueError) as e:
    raise CheckpointError(f"{path}: not a training checkpoint ({e!r})") from None
  if not isinstance(arrays, bytes) or _digest(arrays) != digest:
    raise CheckpointError(f"{path}: corrupt (checksum mismatch)")
  return meta, _unpack(arrays, path)


def restore_hierarchy(path: str, saved: tuple[dict, dict], hierarchy: PHPHierarchy) -> None:
  """Loads the checkpoint's parameters into hierarchy."""
  nnx.update(hierarchy, restore_named(nnx.state(hierarchy, nnx.Param), saved[1]["hierarchy"], path))


def restore_progress(path: str, saved: tuple[dict, dict], model: nnx.Module) -> fitting.Progress:
  """The saved in-progress level's Progress, shaped like a fresh Adam optimizer for `model`."""
  meta, state = saved
  params = nnx.state(model, nnx.Param)
  restored = restore_named((params, optax.adam(0.0).init(params), params), state["progress"], path)
  p = meta["progress"]
  return fitting.Progress(p["iteration"], *restored, p["best_iteration"], p["best_score"],
                          [list(x) for x in p["losses"]])


def decoded_views(saved: tuple[dict, dict]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """The (procedures, counters) [B, T] per finished level > 0: each level's view of every demonstration,
  annotated where strong and decoded where weak."""
  return {int(k): (np.asarray(v["procedures"]), np.asarray(v["counters"]))
          for k, v in saved[1]["decoded"].items()}


def read_decoded(path: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """decoded_views of the training checkpoint at path. Raises CheckpointError if the file is corrupt."""
  saved = read_training(path)
  if saved is None:
    raise FileNotFoundError(f"no training checkpoint at {path}")
  try:
    return decoded_views(saved)
  except (KeyError, TypeError, AttributeError, ValueError) as e:
    raise CheckpointError(f"{path}: no decoded views ({e!r})") from None
