"""What a saved model holds that must not depend on how its run got there (interrupted, resumed, on several
devices): its parameters and its description. The bytes of its Orbax files differ from save to save (their
names and timestamps), so they are compared by what they hold."""
from __future__ import annotations

import json
import pathlib

from flax import nnx

from php_jax.training import checkpoint, resume, storage


def saved_model(workdir: pathlib.Path) -> dict:
  """{"parameters": {name: (dtype, shape, bytes)}, "description": model.json less its file list and checksum}."""
  _, model = checkpoint.load_policy(str(workdir))
  parameters = {name: (value.dtype.str, value.shape, value.tobytes())
                for name, value in storage.named_arrays(nnx.state(model, nnx.Param)).items()}
  description = json.loads((workdir / checkpoint.ARCHITECTURE_FILE).read_text())
  return {"parameters": parameters,
          "description": {k: v for k, v in description.items() if k not in ("files", "sha256")}}


def leftovers(workdir: pathlib.Path) -> list[pathlib.Path]:
  """What a write cut off may leave under workdir and a later run must remove: temporary files and Orbax's
  temporary directories, and training checkpoint steps other than the one its state.json names."""
  found = [p for pattern in (".*.tmp", storage.TEMPORARY) for p in workdir.rglob(pattern)]
  training = workdir / checkpoint.TRAINING_DIR
  if (training / resume.STATE_FILE).exists():
    step = str(json.loads((training / resume.STATE_FILE).read_text())["step"])
    found += [p for p in training.iterdir() if p.name not in (step, resume.STATE_FILE)]
  return found


def file_bytes(directory: pathlib.Path, but: tuple[str, ...] = ()) -> dict[pathlib.Path, bytes]:
  """{path: bytes} of every file under directory (those of its Orbax directories included) but those named in
  `but`."""
  return {p: p.read_bytes() for p in directory.rglob("*") if p.is_file() and p.name not in but}
