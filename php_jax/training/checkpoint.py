"""Saved models: workdir/model.json (task, architecture, and the sha256 of every file of the parameters) and
workdir/model/ (the parameters, an Orbax checkpoint; `storage`). A save writes the parameters, then model.json,
so that a model.json never describes other parameters; a model is read back (`load_policy`) only once its
files match the sums model.json records and its arrays the architecture it describes, else CheckpointError in
one line. The training state a run resumes from is `resume`'s."""
from __future__ import annotations

import json
import os

import jax
from flax import nnx

from php_jax import encoders
from php_jax.data.files import WRITING, write_atomically
from php_jax.envs import tasks
from php_jax.flat import MODEL_CELLS, FlatPolicy
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training.storage import (CheckpointError, check_signed, named_arrays, read_json, restore_arrays,
                                      restore_named, save_arrays, signed)

MODEL_DIR, ARCHITECTURE_FILE, TRAINING_DIR = "model", "model.json", "checkpoint"
MODEL_FILES = (ARCHITECTURE_FILE, MODEL_DIR)  # what load_policy reads
OLDER_FILES = ("model.msgpack", "checkpoint.msgpack", "seeds_checkpoint.msgpack")  # php_jax before Orbax

MAX_CAPACITY = 4096  # counters per level a saved model may claim (a hierarchy file's bound too)
MAX_SIZE = 1 << 20  # observation size, action factor size and procedures per level a saved model may claim


def _save(workdir: str, model, architecture: dict) -> None:
  """workdir/model/ (the parameters), then model.json listing its files' sha256 (so a model.json never
  describes other parameters, even if a save is cut off between the two)."""
  if jax.process_index() != 0:  # of several processes (jax.distributed), the first writes: the others agree
    return
  with WRITING:  # an interrupt waits for model.json too
    files = save_arrays(os.path.join(workdir, MODEL_DIR), named_arrays(nnx.state(model, nnx.Param)))
    write_atomically(os.path.join(workdir, ARCHITECTURE_FILE),
                     json.dumps(signed({**architecture, "files": files}), indent=1).encode())


def _spec_json(spec: HierarchySpec) -> dict:
  observes = None if spec.observes is None else [
      None if level is None else [None if entries is None else list(entries) for entries in level]
      for level in spec.observes]
  return {"name": spec.name, "levels": [list(level) for level in spec.levels],
          "action_sizes": list(spec.action_sizes), "obs_dim": spec.obs_dim,
          **({"observes": observes} if observes is not None else {}),
          **({"observation": encoders.to_json(spec.observation)} if spec.observation is not None else {})}


def save_hierarchy(workdir: str, task_name: str, hierarchy: PHPHierarchy, hidden,
                   capacity: list[int] | None = None) -> None:
  """Writes workdir/model.json (task, hierarchy spec, architecture and, when given, the counter capacity per
  level it was trained with, root first) and workdir/model/ (parameters)."""
  _save(workdir, hierarchy, {"task": task_name, "kind": "php", "spec": _spec_json(hierarchy.spec),
                             "hidden": list(hidden),
                             "tau_in_termination": [level.tau_in_termination for level in hierarchy.levels],
                             "tau_limit": [level.tau_limit for level in hierarchy.levels],
                             "allowed_ops": [level.allowed_ops for level in hierarchy.levels],
                             **({"trunk": trunk_width(hierarchy)} if trunk_width(hierarchy) else {}),
                             **({"memory": hierarchy.memory} if hierarchy.memory else {}),
                             **({"end_given": True} if hierarchy.end_given else {}),
                             **({"capacity": list(capacity)} if capacity else {})})


def trunk_width(hierarchy: PHPHierarchy) -> int | None:
  """The width of the hierarchy's per-level trunks (`encoders.Encoder`), None where it has none."""
  trunk = hierarchy.levels[0].trunk
  return None if trunk is None else trunk.width


def save_flat(workdir: str, task_name: str, policy: FlatPolicy, spec: HierarchySpec) -> None:
  """A flat baseline (LSTM or GRU), in the same two files."""
  _save(workdir, policy, {"task": task_name, "kind": policy.name, "spec": _spec_json(spec),
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
    observation = spec.get("observation")
    if observation is not None:
      observation = encoders.from_json(observation, "\"observation\"")
    saved = HierarchySpec(str(spec["name"]), tuple(tuple(map(str, level)) for level in spec["levels"]),
                          tuple(int(n) for n in spec["action_sizes"]), int(spec["obs_dim"]), observes=observes,
                          observation=observation)
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
  architecture = read_json(path)
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
  if kind in MODEL_CELLS and isinstance(hidden, int) and hidden > 0:
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


def load_policy(workdir: str) -> tuple[str, PHPHierarchy | FlatPolicy]:
  """(task name, model) saved by save_hierarchy or save_flat. Raises FileNotFoundError if workdir holds
  no model, CheckpointError if its files are corrupt or disagree with each other."""
  arch_path, model_path = (os.path.join(workdir, f) for f in (ARCHITECTURE_FILE, MODEL_DIR))
  if os.path.isfile(arch_path) and not os.path.isdir(model_path) and os.path.isfile(model_path + ".msgpack"):
    raise CheckpointError(f"{model_path}.msgpack was saved by an older php_jax; train the model again")
  if not (os.path.isfile(arch_path) and os.path.isdir(model_path)):
    raise FileNotFoundError(f"no trained model in {workdir!r} (expected {ARCHITECTURE_FILE} and {MODEL_DIR}/)")
  architecture = read_json(arch_path)
  task_name, kind, hidden, tau = _architecture(arch_path, architecture)
  check_signed(arch_path, architecture)
  named = restore_arrays(model_path, architecture.get("files"), arch_path)
  spec = _saved_spec(arch_path, architecture)
  if kind in MODEL_CELLS:
    def build():
      return FlatPolicy(spec.obs_dim, spec.action_sizes, hidden, spec.observation, cell=MODEL_CELLS[kind],
                        rngs=nnx.Rngs(0))
  else:
    tau_in_termination, tau_limit = tau
    if len(tau_in_termination) != spec.num_levels:
      raise CheckpointError(f"{arch_path}: tau_in_termination has {len(tau_in_termination)} entries; {task_name} "
                            f"has {spec.num_levels} levels")
    allowed_ops = _saved_allowed_ops(arch_path, architecture, spec)
    trunk, memory = architecture.get("trunk"), architecture.get("memory")
    for key, width in (("trunk", trunk), ("memory", memory)):
      if not (width is None or (isinstance(width, int) and not isinstance(width, bool) and 1 <= width <= MAX_SIZE)):
        raise CheckpointError(f"{arch_path}: \"{key}\" must be an integer in 1..{MAX_SIZE}; got {str(width)[:80]}")

    end_given = architecture.get("end_given", False)
    if not isinstance(end_given, bool):
      raise CheckpointError(f"{arch_path}: \"end_given\" must be true or false; got {str(end_given)[:80]}")

    def build():
      return PHPHierarchy(spec, hidden=hidden, tau_in_termination=tau_in_termination, tau_limit=tau_limit,
                          allowed_ops=allowed_ops, trunk=trunk, memory=memory, end_given=end_given,
                          rngs=nnx.Rngs(0))
  model = nnx.eval_shape(build)  # its shapes only: every parameter comes from the file (and no state but them)
  nnx.update(model, restore_named(nnx.state(model, nnx.Param), named, model_path))
  return task_name, model
