"""Decoding demonstrations with a trained hierarchy: exact inference over its whole call stack
(`stack_lattice`), with the hierarchy's own networks at every level (no stand-in root).

For each demonstration: log P(actions | observations) under the hierarchy, summed over every stack path
(counters within the capacities), the most likely stack at every step, and how likely each procedure is to
be running at every level and step.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import numpy as np

from php_jax.demos import Demonstration
from php_jax.inference import stack_lattice
from php_jax.model import PHPHierarchy
from php_jax.training.objective import stack_query


class Decoded(NamedTuple):
  """Per demonstration [B]: log_likelihood (float), and the most likely stack procedures / counters
  [B, T, d] (root first; −1 on padding, and at every step of a demonstration no stack fits)."""
  log_likelihood: np.ndarray
  procedures: np.ndarray
  counters: np.ndarray


def decode(hierarchy: PHPHierarchy, capacity: tuple[int, ...], batch: Demonstration,
           chunk: int = 512) -> Decoded:
  """Decodes every demonstration of batch [B, ...], `chunk` at a time (chunks padded to one shape, so the
  computation compiles once per demonstration length)."""
  return Decoded(*_chunked(functools.partial(stack_query, hierarchy, capacity, _most_likely), batch, chunk))


def log_likelihood_per_step(log_likelihood: np.ndarray, length: np.ndarray) -> tuple[float | None, int]:
  """(Σ log P / Σ length over the demonstrations some stack fits (finite log_likelihood [B]), or None if
  none does; how many fit none). Of held-out demonstrations, an unsupervised score for comparing runs, or
  restarts, without an environment."""
  fits = np.isfinite(log_likelihood)
  steps = int(np.sum(np.asarray(length)[fits]))
  return (float(np.sum(log_likelihood[fits], dtype=np.float64)) / steps if fits.any() else None), int(np.sum(~fits))


def explain(hierarchy: PHPHierarchy, capacity: tuple[int, ...], batch: Demonstration,
            chunk: int = 512) -> tuple[Decoded, tuple[np.ndarray, ...]]:
  """decode, and per level, root first, [B, T, K_i] P(level i runs procedure h at step t | actions,
  observations): the posterior frame marginals summed over counters (zero on padding); one program."""
  *decoded, marginals = _chunked(functools.partial(stack_query, hierarchy, capacity, _most_likely_and_marginals),
                                 batch, chunk)
  return Decoded(*decoded), marginals


def _chunked(run, batch: Demonstration, chunk: int) -> list:
  """run(observations, actions, length) → a tuple of [B, ...] arrays (or of tuples of them), over batch
  `chunk` at a time."""
  num = len(batch.length)
  size = min(chunk, num)
  parts = []
  for start in range(0, num, size):
    index = np.minimum(np.arange(start, start + size), num - 1)  # the last chunk repeats its last row
    obs, act, length = (np.asarray(x)[index] for x in (batch.observations, batch.actions, batch.length))
    parts.append(jax.device_get(run(obs, act, length)))
  return [jax.tree.map(lambda *p: np.concatenate(p)[:num], *part) for part in zip(*parts)]


def _most_likely(inputs: stack_lattice.StackInputs):
  path = stack_lattice.viterbi(inputs)
  return stack_lattice.log_likelihood(inputs), path.procedures, path.counters


def _most_likely_and_marginals(inputs: stack_lattice.StackInputs):
  posterior = stack_lattice.forward_backward(inputs)
  path = stack_lattice.viterbi(inputs)
  return (posterior.log_likelihood, path.procedures, path.counters,
          tuple(m.sum(-1) for m in posterior.marginals))
