"""Decoding demonstrations with a trained hierarchy: exact inference over its whole call stack
(`stack_lattice`), with the hierarchy's own networks at every level (no stand-in root).

For each demonstration: log P(actions | observations) under the hierarchy, summed over every stack path
(counters within the capacities), and the most likely stack at every step.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import numpy as np

from php_jax import stack_lattice
from php_jax.demos import Demonstration
from php_jax.model import PHPHierarchy
from php_jax.objective import stack_inputs


class Decoded(NamedTuple):
  """Per demonstration [B]: log_likelihood (float), and the most likely stack procedures / counters
  [B, T, d] (root first; −1 on padding)."""
  log_likelihood: np.ndarray
  procedures: np.ndarray
  counters: np.ndarray


def decode(hierarchy: PHPHierarchy, capacity: tuple[int, ...], batch: Demonstration,
           chunk: int = 512) -> Decoded:
  """Decodes every demonstration of batch [B, ...], `chunk` at a time (chunks padded to one shape, so the
  computation compiles once per demonstration length)."""
  run = _compiled(hierarchy, tuple(capacity))
  num = len(batch.length)
  size = min(chunk, num)
  parts = []
  for start in range(0, num, size):
    index = np.minimum(np.arange(start, start + size), num - 1)  # the last chunk repeats its last row
    obs, act, length = (np.asarray(x)[index] for x in (batch.observations, batch.actions, batch.length))
    parts.append(jax.device_get(run(obs, act, length)))
  log_likelihood, procs, taus = (np.concatenate(p)[:num] for p in zip(*parts))
  return Decoded(log_likelihood, procs, taus)


def _compiled(hierarchy: PHPHierarchy, capacity: tuple[int, ...]):
  @jax.jit
  def run(observations, actions, length):
    def one(obs, act, n):
      inputs = stack_inputs(hierarchy, capacity, obs, act, n)
      path = stack_lattice.viterbi(inputs)
      return stack_lattice.log_likelihood(inputs), path.procedures, path.counters
    return jax.vmap(one)(observations, actions, length)
  return run
