"""Replaying demonstrations: does a hierarchy's argmax policy, run on a demonstration's recorded
observations, take every recorded action and return from its root right after the last one? (For a hierarchy
whose demonstrations end where their environment ended them, `end_given`, taking every recorded action is
enough: the environment, not the root, ends such an episode.)

The recorded demonstration is an environment (`Recording`) for the executor: its state is the demonstration
and a step index; observe gives the recorded observation, and an action other than the recorded one (or any
action after the last) fails. The hierarchy then runs in the executor unchanged.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from php_jax.demos import Demonstration
from php_jax.envs import evaluation
from php_jax.hierarchy import HierarchySpec


class RecordingState(NamedTuple):
  """One demonstration being replayed. observations [T+1, D], actions [T, F], length [], step [], failed []."""
  observations: jax.Array
  actions: jax.Array
  length: jax.Array
  step: jax.Array
  failed: jax.Array


class Recording:
  """The executor's environment for replay (stateless: the demonstration lives in the state)."""

  @staticmethod
  def observe(state: RecordingState) -> jax.Array:
    return state.observations[state.step]

  @staticmethod
  def step(state: RecordingState, action: jax.Array) -> RecordingState:
    index = jnp.minimum(state.step, state.actions.shape[0] - 1)
    wrong = (state.step >= state.length) | jnp.any(action != state.actions[index])
    return state._replace(step=state.step + 1, failed=state.failed | wrong)


RECORDING = Recording()  # one instance: the executor compiles once per shape, not once per call
REPLAY_CHUNK = 1024  # demonstrations replayed at once (`replay`)


class Replay(NamedTuple):
  """Per demonstration [B]: replayed (bool) and first_mismatch (int32: the first step whose action differs
  from the recorded one, or that comes after the last, or where the root returned too early; −1 if none)."""
  replayed: np.ndarray
  first_mismatch: np.ndarray


def replay(policy, spec: HierarchySpec, batch: Demonstration, key: jax.Array | None = None,
           chunk: int = REPLAY_CHUNK) -> Replay:
  """Runs policy (an argmax hierarchy, or a flat baseline, whose root returning is its stopping) on each
  demonstration of batch [B, ...]; see the module docstring. Above `chunk` demonstrations, they run chunk at a
  time (the last chunk padded with copies of its first), so the rollout's memory is bounded by the chunk."""
  num = batch.length.shape[0]
  if not (isinstance(chunk, int) and not isinstance(chunk, bool) and chunk >= 1):
    raise ValueError(f"chunk must be a positive integer; got {chunk!r}")
  keys = jax.random.split(jax.random.key(0) if key is None else key, num)
  size = max(1, min(num, chunk))
  parts = [Replay(np.zeros(0, bool), np.zeros(0, np.int32))]  # an empty batch's result, and the start of any other's
  for start in range(0, num, size):
    rows = np.arange(start, min(start + size, num))
    padded = np.concatenate([rows, np.full(size - len(rows), start)])
    part = _replay_rows(policy, spec, batch, keys, padded, int(batch.actions.shape[1]) + 1)
    parts.append(Replay(*(x[:len(rows)] for x in part)))
  return Replay(*(np.concatenate(field) for field in zip(*parts)))


def _replay_rows(policy, spec: HierarchySpec, batch: Demonstration, keys: jax.Array, rows: np.ndarray,
                 max_steps: int) -> Replay:
  """The `Replay` of batch's rows, each run for at most max_steps."""
  observations, actions, length = (np.asarray(x)[rows] for x in (batch.observations, batch.actions, batch.length))
  states = RecordingState(jnp.asarray(observations), jnp.asarray(actions), jnp.asarray(length),
                          jnp.zeros(len(rows), jnp.int32), jnp.zeros(len(rows), bool))
  rollout = evaluation.rollout(policy, spec, RECORDING, states, keys[rows], max_steps)
  steps = np.asarray(rollout.length)
  # A failed step is the episode's last; a root returning early ends the episode at `steps` < length.
  first = np.where(np.asarray(rollout.valid), steps, steps - 1)
  if getattr(policy, "end_given", False):  # an action after the last (first = length) is not the demonstration's
    replayed = first >= length
  else:
    replayed = np.asarray(rollout.terminated) & (steps == length)
  return Replay(replayed, np.where(replayed, -1, first).astype(np.int32))


def replayed_fraction(policy, spec: HierarchySpec, batch: Demonstration) -> float:
  """Fraction of batch's demonstrations that policy replays."""
  return float(np.mean(replay(policy, spec, batch).replayed))
