"""Saving and loading trained models (PHP hierarchies and the flat LSTM baseline): parameters as msgpack
(flax.serialization), the architecture as JSON, each written atomically (a temporary file renamed into
place), so a workdir never holds half a model."""
from __future__ import annotations

import contextlib
import json
import os
import secrets

from flax import nnx, serialization

from php_jax import tasks
from php_jax.flat_lstm import FlatLSTMPolicy
from php_jax.model import PHPHierarchy

MODEL_FILE, ARCHITECTURE_FILE = "model.msgpack", "model.json"


def write_atomically(path: str, data: bytes) -> None:
  """Writes data to path through a temporary file in the same directory renamed into place: readers see the
  old file or the new one, never part of one. The file gets mode 0o666 & ~umask (0644 under umask 022), as
  open() would give it; if the write or the rename fails (KeyboardInterrupt included) the temporary file is
  removed."""
  directory = os.path.dirname(os.path.abspath(path))
  os.makedirs(directory, exist_ok=True)
  while True:  # O_CREAT | O_EXCL with mode 0o666: the kernel applies the umask, no need to read or change it
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
    try:
      fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
      break
    except FileExistsError:
      continue
  try:
    with os.fdopen(fd, "wb") as f:
      f.write(data)
    os.replace(tmp, path)
  except BaseException:
    with contextlib.suppress(OSError):
      os.unlink(tmp)
    raise


def _save(workdir: str, model, architecture: dict) -> None:
  params = nnx.to_pure_dict(nnx.state(model, nnx.Param))
  write_atomically(os.path.join(workdir, MODEL_FILE), serialization.msgpack_serialize(params))
  write_atomically(os.path.join(workdir, ARCHITECTURE_FILE), json.dumps(architecture, indent=1).encode())


def save_hierarchy(workdir: str, task_name: str, hierarchy: PHPHierarchy, hidden, tau_in_termination) -> None:
  """Writes workdir/model.json (task and architecture) and workdir/model.msgpack (parameters)."""
  _save(workdir, hierarchy, {"task": task_name, "kind": "php", "hidden": list(hidden),
                             "tau_in_termination": list(tau_in_termination)})


def save_flat_lstm(workdir: str, task_name: str, policy: FlatLSTMPolicy) -> None:
  """The flat LSTM baseline, in the same two files."""
  _save(workdir, policy, {"task": task_name, "kind": "flat_lstm", "hidden": policy.hidden})


def load_policy(workdir: str) -> tuple[str, PHPHierarchy | FlatLSTMPolicy]:
  """(task name, model) saved by save_hierarchy or save_flat_lstm. Raises FileNotFoundError if workdir holds
  no model."""
  arch_path, model_path = (os.path.join(workdir, f) for f in (ARCHITECTURE_FILE, MODEL_FILE))
  if not (os.path.isfile(arch_path) and os.path.isfile(model_path)):
    raise FileNotFoundError(f"no trained model in {workdir!r} (expected {ARCHITECTURE_FILE} and {MODEL_FILE})")
  with open(arch_path) as f:
    architecture = json.load(f)
  task = tasks.get(architecture["task"])
  if architecture.get("kind", "php") == "flat_lstm":
    model = FlatLSTMPolicy(task.spec.obs_dim, task.spec.action_sizes, architecture["hidden"], rngs=nnx.Rngs(0))
  else:
    model = PHPHierarchy(task.spec, hidden=tuple(architecture["hidden"]),
                         tau_in_termination=tuple(architecture["tau_in_termination"]), rngs=nnx.Rngs(0))
  state = nnx.state(model, nnx.Param)
  with open(model_path, "rb") as f:
    nnx.replace_by_pure_dict(state, serialization.msgpack_restore(f.read()))
  nnx.update(model, state)
  return task.name, model
