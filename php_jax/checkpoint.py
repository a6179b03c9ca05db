"""Saving and loading trained hierarchies: parameters as msgpack (flax.serialization), the architecture as
JSON, each written atomically (a temporary file renamed into place), so a workdir never holds half a model."""
from __future__ import annotations

import json
import os
import tempfile

from flax import nnx, serialization

from php_jax import tasks
from php_jax.model import PHPHierarchy

MODEL_FILE, ARCHITECTURE_FILE = "model.msgpack", "model.json"


def write_atomically(path: str, data: bytes) -> None:
  directory = os.path.dirname(os.path.abspath(path))
  os.makedirs(directory, exist_ok=True)
  with tempfile.NamedTemporaryFile("wb", dir=directory, delete=False, suffix=".tmp") as f:
    f.write(data)
  os.replace(f.name, path)


def save_hierarchy(workdir: str, task_name: str, hierarchy: PHPHierarchy, hidden, tau_in_termination) -> None:
  """Writes workdir/model.json (task and architecture) and workdir/model.msgpack (parameters)."""
  params = nnx.to_pure_dict(nnx.state(hierarchy, nnx.Param))
  write_atomically(os.path.join(workdir, MODEL_FILE), serialization.msgpack_serialize(params))
  architecture = {"task": task_name, "hidden": list(hidden), "tau_in_termination": list(tau_in_termination)}
  write_atomically(os.path.join(workdir, ARCHITECTURE_FILE), json.dumps(architecture, indent=1).encode())


def load_hierarchy(workdir: str) -> tuple[str, PHPHierarchy]:
  """(task name, hierarchy) saved by save_hierarchy. Raises FileNotFoundError if workdir holds no model."""
  arch_path, model_path = (os.path.join(workdir, f) for f in (ARCHITECTURE_FILE, MODEL_FILE))
  if not (os.path.isfile(arch_path) and os.path.isfile(model_path)):
    raise FileNotFoundError(f"no trained model in {workdir!r} (expected {ARCHITECTURE_FILE} and {MODEL_FILE})")
  with open(arch_path) as f:
    architecture = json.load(f)
  task = tasks.get(architecture["task"])
  hierarchy = PHPHierarchy(task.spec, hidden=tuple(architecture["hidden"]),
                           tau_in_termination=tuple(architecture["tau_in_termination"]), rngs=nnx.Rngs(0))
  state = nnx.state(hierarchy, nnx.Param)
  with open(model_path, "rb") as f:
    nnx.replace_by_pure_dict(state, serialization.msgpack_restore(f.read()))
  nnx.update(hierarchy, state)
  return task.name, hierarchy
