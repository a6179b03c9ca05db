"""Bubble sort on a tape of digits, as pure jittable state transitions.

A tape of n ≥ 2 digits at positions 0..n-1 (the tape array is padded to a static width W ≥ n + 1 with
EMPTY, so position n reads EMPTY) and three pointers: i and j (the compared pair) and e (the end of the
unsorted region), starting at i = 0, j = 1, e = n. Observation: the symbols under i and j, one-hot (2 × 11),
then the bits i = 0 and j = e: 24 floats. Elementary action: int32 [3] = (kind, pointer, direction) with
kind MOVE or SWAP, pointer i, j or e, direction LEFT (−1) or RIGHT (+1). SWAP exchanges the digits under i
and j and must name (i, LEFT), with i and j in 0..n-1; a MOVE must keep its pointer in 0..n. Anything else is
an invalid action: it marks the episode failed and changes nothing else.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

EMPTY = 10
NUM_SYMBOLS = 11
MOVE, SWAP = 0, 1
I, J, E = 0, 1, 2
LEFT, RIGHT = 0, 1
ACTION_SIZES = (2, 3, 2)
OBS_DIM = 2 * NUM_SYMBOLS + 2


@struct.dataclass
class State:
  """tape: [W] int32 symbols; size: [] int32 n; pointers: [3] int32 (i, j, e); failed: [] bool."""
  tape: jax.Array
  size: jax.Array
  pointers: jax.Array
  failed: jax.Array


def make_problem(array, width: int | None = None) -> State:
  """The start state for a list of n ≥ 2 digits (integers, bool not), on a tape of width ≥ n + 1 (default
  n + 1)."""
  if any(isinstance(d, (bool, np.bool_)) or not isinstance(d, (int, np.integer)) for d in array):
    raise ValueError(f"an array must hold integer digits 0-9; got {list(array)}")
  if width is not None and (isinstance(width, bool) or not isinstance(width, (int, np.integer))):
    raise ValueError(f"width must be an integer; got {width!r}")
  array = [int(d) for d in array]
  if len(array) < 2 or not all(0 <= d <= 9 for d in array):
    raise ValueError(f"an array must hold at least 2 digits 0-9; got {array}")
  width = len(array) + 1 if width is None else width
  if width < len(array) + 1:
    raise ValueError(f"width {width} is too small for {len(array)} digits (need {len(array) + 1})")
  tape = np.full(width, EMPTY, np.int32)
  tape[:len(array)] = array
  return State(jnp.asarray(tape), jnp.int32(len(array)), jnp.array([0, 1, len(array)], jnp.int32),
               jnp.zeros((), bool))


def observe(state: State) -> jax.Array:
  """[24] float32: one-hot symbols under i and j, then (i = 0, j = e)."""
  i, j, e = state.pointers[I], state.pointers[J], state.pointers[E]
  symbols = jax.nn.one_hot(state.tape[jnp.stack([i, j])], NUM_SYMBOLS, dtype=jnp.float32).reshape(-1)
  return jnp.concatenate([symbols, jnp.stack([i == 0, j == e]).astype(jnp.float32)])


def step(state: State, action: jax.Array) -> State:
  """Applies action (kind, pointer, direction); an invalid action only sets failed."""
  kind, pointer, direction = action[0], action[1], action[2]
  in_range = (kind >= 0) & (kind <= SWAP) & (pointer >= 0) & (pointer <= E) & (direction >= 0) & (
      direction <= RIGHT)
  index = jnp.clip(pointer, 0, E)
  moved = state.pointers[index] + jnp.where(direction == LEFT, -1, 1)
  move_ok = (moved >= 0) & (moved <= state.size)
  i, j = state.pointers[I], state.pointers[J]
  swap_ok = (pointer == I) & (direction == LEFT) & (i >= 0) & (i < state.size) & (j >= 0) & (j < state.size)
  ok = in_range & jnp.where(kind == MOVE, move_ok, swap_ok)
  swap = ok & (kind == SWAP)
  tape = state.tape.at[i].set(jnp.where(swap, state.tape[j], state.tape[i]))
  tape = tape.at[j].set(jnp.where(swap, state.tape[i], state.tape[j]))
  pointers = state.pointers.at[index].set(jnp.where(ok & (kind == MOVE), moved, state.pointers[index]))
  return State(tape, state.size, pointers, state.failed | ~ok)


def result(state: State) -> list[int]:
  """The tape's n digits (host side)."""
  return [int(d) for d in np.asarray(state.tape)[:int(state.size)]]


def oracle_step_budget(size: int) -> int:
  """Elementary steps the oracle needs at most for n = size digits: per pass over an unsorted region of e
  digits, e − 1 compare-and-shifts of at most 3 steps, then 1 + 2(e − 1) to move e and reset i and j."""
  return 5 * size * (size - 1) // 2 + size - 1
