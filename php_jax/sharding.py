"""Data parallelism: a batch's leading axis split over a 1-D mesh of every device (axis "data"), parameters
replicated, one jitted program (no pmap).

Training (`levelwise.train_level`, `joint.train_joint`, `levelwise.train_seeds`) shards its length buckets over
`data_mesh()` whenever more than one device is present. A batch whose size is not a multiple of the device
count is padded with copies of its first entry (valid data, so their log-likelihoods and gradients are
finite), marked False in a `real` mask: the losses weigh them 0 and divide by the number of real entries.
Arrays are built with `jax.make_array_from_callback`, each process placing its own devices' parts of the whole
batch (which every process builds alike from the seed), so the mesh may span the processes of
`jax.distributed`.
"""
from __future__ import annotations

from typing import Any, TypeVar

import jax
import jax.numpy as jnp
import numpy as np
from jax.sharding import Mesh, NamedSharding, PartitionSpec

AXIS = "data"
Batch = TypeVar("Batch")


def data_mesh() -> Mesh | None:
  """A 1-D mesh (axis "data") over every device of every process; None when there is one device."""
  devices = jax.devices()
  return Mesh(np.asarray(devices), (AXIS,)) if len(devices) > 1 else None


def one_program_at_a_time(mesh: Mesh | None) -> bool:
  """Whether a loop over programs that run on mesh must wait for each before dispatching the next: on CPU
  devices (XLA_FLAGS=--xla_force_host_platform_device_count=N), whose collectives meet in XLA's in-process
  rendezvous. With several such programs in flight on a loaded machine, one device can fall behind by over
  that rendezvous' 40-second limit, and XLA aborts the process; one program at a time, every device joins
  each all-reduce together."""
  return mesh is not None and mesh.devices.flat[0].platform == "cpu"


def pad(batch: Batch, mesh: Mesh | None) -> tuple[Batch, np.ndarray]:
  """batch (a pytree of host arrays [B, ...]) with copies of its first entry appended up to a multiple of mesh's
  device count (none without a mesh), and real [B'] bool: False on the copies."""
  size = len(jax.tree.leaves(batch)[0])
  extra = -size % mesh.size if mesh is not None else 0
  index = np.concatenate([np.arange(size), np.zeros(extra, int)])
  return jax.tree.map(lambda x: np.asarray(x)[index], batch), np.arange(size + extra) < size


def put(batch: Batch, mesh: Mesh | None, axis: int = 0) -> Batch:
  """batch's host arrays [..., B, ...] (B at `axis`) as device arrays: split along B over mesh's devices (B a
  multiple of their count), or as `jnp.asarray` gives them without a mesh."""
  if mesh is None:
    return jax.tree.map(jnp.asarray, batch)
  sharding = NamedSharding(mesh, PartitionSpec(*[None] * axis, AXIS))
  return jax.tree.map(lambda x: jax.make_array_from_callback(np.shape(x), sharding,
                                                             lambda index: np.asarray(x)[index]), batch)


def replicate(tree: Any, mesh: Mesh | None) -> Any:
  """tree's arrays, whole on every device of mesh (tree itself without a mesh)."""
  if mesh is None:
    return tree
  sharding = NamedSharding(mesh, PartitionSpec())
  return jax.tree.map(lambda x: jax.make_array_from_callback(np.shape(x), sharding,
                                                             lambda index: np.asarray(x)[index]), tree)


def unreplicate(tree: Any, mesh: Mesh | None) -> Any:
  """tree's replicated arrays as arrays of the default device (tree itself without a mesh): what evaluation and
  decoding run on, so that they do not run again on every device."""
  if mesh is None:
    return tree
  return jax.tree.map(lambda x: jnp.asarray(np.asarray(x)), tree)
