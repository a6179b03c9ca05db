"""Resuming a run: the training checkpoint it writes as it goes, and the check that a checkpoint was made with
this run's settings before it is resumed.

A training checkpoint is the directory workdir/checkpoint/: state.json (per run trained: the level, the
settings it was made with, the report so far, the optimizer's progress; the step and its files' sha256) and
the step it names, an Orbax checkpoint of the arrays (`storage`; per run: the hierarchy's parameters, the
optimizer state of the level in progress, the decoded views of finished levels). A save writes the new step,
then state.json (a temporary file renamed into place), then removes the older step: a reader sees the old
checkpoint or the new one, never part of one, and a save cut off leaves only what the next save removes.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
import os
from typing import Callable

import jax
import numpy as np
import optax
from flax import nnx

from php_jax import fitting
from php_jax.data.files import WRITING, write_atomically
from php_jax.demos import Demonstration
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training.config import TrainConfig
from php_jax.training.storage import (CheckpointError, check_signed, named_arrays, part, read_json, remove_saved,
                                      restore_arrays, restore_named, save_arrays, signed)

STATE_FILE = "state.json"  # in a training checkpoint: the step to read and what it holds


def write_training(path: str, hierarchy: PHPHierarchy, meta: dict, progress: fitting.Progress | None,
                   decoded: dict[int, tuple[np.ndarray, np.ndarray]]) -> None:
  """A training checkpoint at path (a directory): the hierarchy's parameters, the in-progress level's
  optimizer state (progress), the decoded views of finished levels, and meta (JSON: the level, the settings,
  the report so far)."""
  write_training_seeds(path, [(hierarchy, meta, progress, decoded)])


def write_training_seeds(path: str, states: list[tuple]) -> None:
  """One checkpoint holding several seeds' training states, each (hierarchy, meta, progress, decoded) as
  write_training takes them (`levelwise.train_seeds`): saved at once, so the seeds never disagree on where they
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
    files = save_arrays(os.path.join(path, step), named)
    try:
      write_atomically(os.path.join(path, STATE_FILE), json.dumps(signed({"states": metas, "step": int(step),
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
  state = read_json(state_path)
  if not (isinstance(state, dict) and isinstance(state.get("states"), list) and state["states"]
          and all(isinstance(m, dict) and "level" in m and "progress" in m for m in state["states"])):
    raise CheckpointError(f"{state_path}: not a training checkpoint's state")
  check_signed(state_path, state)
  named = restore_arrays(os.path.join(path, str(state.get("step"))), state.get("files"), state_path)
  return [(meta, part(named, str(s))) for s, meta in enumerate(state["states"])]


def restore_hierarchy(path: str, saved: tuple[dict, dict], hierarchy: PHPHierarchy) -> None:
  """Loads the checkpoint's parameters into hierarchy."""
  nnx.update(hierarchy, restore_named(nnx.state(hierarchy, nnx.Param), part(saved[1], "hierarchy"), path))


def restore_progress(path: str, saved: tuple[dict, dict], model: nnx.Module) -> fitting.Progress:
  """The saved in-progress level's Progress, shaped like a fresh Adam optimizer for `model`."""
  meta, named = saved
  params = nnx.state(model, nnx.Param)
  restored = restore_named((params, optax.adam(0.0).init(params), params), part(named, "progress"), path)
  p = meta["progress"]
  return fitting.Progress(p["iteration"], *restored, p["best_iteration"], p["best_score"],
                          [list(x) for x in p["losses"]])


def decoded_views(saved: tuple[dict, dict]) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """The (procedures, counters) [B, T] per finished level > 0: each level's view of every demonstration,
  annotated where strong and decoded where weak."""
  decoded = part(saved[1], "decoded")
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


_DIGESTED_ROWS = 1024


def run_settings(spec: HierarchySpec, demos: Demonstration, config: TrainConfig) -> dict:
  """What a checkpoint must have been made with to be resumed: the config, the hierarchy and a digest of the
  demonstrations (so another seed, data set or annotation is noticed; their observations' values, not the
  type that holds them)."""
  digest = hashlib.sha256()
  for name, array in zip(demos._fields, demos):
    array = np.asarray(array)
    if name == "observations":  # as float32, whatever type holds them, a block of rows at a time
      for start in range(0, len(array), _DIGESTED_ROWS):
        digest.update(np.ascontiguousarray(array[start:start + _DIGESTED_ROWS], np.float32).tobytes())
    else:
      digest.update(np.ascontiguousarray(array).tobytes())
  settings = {"config": dataclasses.asdict(config), "levels": spec.levels, "demonstrations": digest.hexdigest(),
              **({"observes": spec.observes} if spec.observes is not None else {})}
  return json.loads(json.dumps(settings))  # as a checkpoint stores it: tuples become lists


# Settings whose default differs from what runs did before the setting existed.
_BEFORE_THEY_EXISTED = {"snapshot": "earliest", "anneal_temperature": 1.0, "training": "levelwise",
                        "segment_iterations": 0, "split_rounds": 0, "length_buckets": 4}


# Settings that runs recorded unset before a run resolved them, and what unset meant then.
_UNSET_MEANT = {"batch_size": 0}


def saved_config(saved: dict) -> dict:
  """A config a run recorded (JSON), with every setting it does not name (it predates the setting) as what
  runs did before it: its default, or _BEFORE_THEY_EXISTED's value; and a setting recorded unset before runs
  resolved it as what unset meant then (_UNSET_MEANT)."""
  config = {**dataclasses.asdict(TrainConfig()), **_BEFORE_THEY_EXISTED, **saved}
  config.update({name: meant for name, meant in _UNSET_MEANT.items() if config.get(name) is None})
  return json.loads(json.dumps(config))


_WHY = {"demonstrations": " (another seed, number of demonstrations or of annotated ones, or data file; the "
                          "balanced strong_weight follows them)", "levels": " (another hierarchy)",
        "observes": " (another hierarchy: what its procedures observe)"}


def check_resumable(path: str, saved_settings: dict, settings: dict) -> None:
  """Raises CheckpointError naming the settings that differ between a checkpoint and this run (a setting the
  checkpoint does not name: `saved_config`)."""
  saved_settings = {**saved_settings, "config": saved_config(saved_settings.get("config", {}))}
  if saved_settings == settings:
    return
  old_config, new_config = saved_settings["config"], settings["config"]
  differ = [f"{k} differ{_WHY[k]}" for k in ("demonstrations", "levels", "observes")
            if saved_settings.get(k) != settings.get(k)]
  differ += [f"{k}: {old_config.get(k)!r} there, {v!r} here" for k, v in new_config.items() if old_config.get(k) != v]
  raise CheckpointError(f"{path} was made with other settings ({'; '.join(differ) or 'unknown'}); "
                                   "use a fresh workdir, or --overwrite to start again")


def resume_from(path: str, saved: tuple[dict, dict], settings: dict, hierarchy: PHPHierarchy) -> dict:
  """Restores a read training checkpoint's parameters into hierarchy once its settings are this run's
  (else CheckpointError naming those that differ); returns the row a resumed run logs first."""
  meta = saved[0]
  check_resumable(path, meta.get("settings", {}), settings)
  restore_hierarchy(path, saved, hierarchy)
  return {"resumed": True, "level": meta["level"], "iteration": meta["progress"] and meta["progress"]["iteration"],
          "logged": meta["logged"]}


class CountedLog:
  """log(row), counting the rows: a checkpoint records how many were logged before it, so that a resumed
  run knows which rows of its metrics stay valid."""

  def __init__(self, log: Callable[[dict], None]):
    self.log, self.logged = log, 0

  def __call__(self, row: dict) -> None:
    self.logged += 1
    self.log(row)

  def resumed(self, row: dict) -> None:
    """Logs a resume_from row (not counted: the rows logged before it are)."""
    self.logged = row["logged"]
    self.log(row)
