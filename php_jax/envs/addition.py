"""Long-hand addition on four tapes (paper §5.2), as pure jittable state transitions.

Tapes in1, in2, carry, out of static width W; column 0 is the least significant digit. A cell holds a digit
0–9 or EMPTY. The observation is the four symbols under the heads, one-hot: 4 × 11 floats. An elementary
action is int32 [3] = (kind, tape, arg): MOVE (arg LEFT = 0 towards more significant, RIGHT = 1) or WRITE
(arg = digit). A MOVE with another arg or off the tape marks the episode failed and changes nothing else.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

EMPTY = 10
NUM_SYMBOLS = 11
NUM_TAPES = 4
IN1, IN2, CARRY, OUT = range(NUM_TAPES)
MOVE, WRITE = 0, 1
LEFT, RIGHT = 0, 1
ACTION_SIZES = (2, NUM_TAPES, 10)
OBS_DIM = NUM_TAPES * NUM_SYMBOLS
TAPE_NAMES = ("in1", "in2", "carry", "out")


@struct.dataclass
class State:
  """tapes: [4, W] int32 symbols; heads: [4] int32 columns; failed: [] bool (an invalid action was taken)."""
  tapes: jax.Array
  heads: jax.Array
  failed: jax.Array


def width_for(num_digits: int) -> int:
  """Smallest tape width that fits a sum of two num_digits numbers and the final left shift."""
  return num_digits + 2


def make_problem(a: str, b: str, width: int | None = None) -> State:
  """The start state for a + b, two decimal strings of equal length (most significant digit first)."""
  if not (isinstance(a, str) and isinstance(b, str)):
    raise ValueError(f"a and b must be decimal strings (not numbers: leading zeros count); got {a!r}, {b!r}")
  if width is not None and (isinstance(width, bool) or not isinstance(width, (int, np.integer))):
    raise ValueError(f"width must be an integer; got {width!r}")
  if len(a) != len(b) or not a or not (a + b).isdigit() or not (a + b).isascii():
    raise ValueError(f"a and b must be non-empty decimal strings of equal length; got {a!r}, {b!r}")
  width = width_for(len(a)) if width is None else width
  if width < width_for(len(a)):
    raise ValueError(f"width {width} is too small for {len(a)} digits (need {width_for(len(a))})")
  tapes = np.full((NUM_TAPES, width), EMPTY, np.int32)
  tapes[IN1, :len(a)] = [int(c) for c in reversed(a)]
  tapes[IN2, :len(b)] = [int(c) for c in reversed(b)]
  return State(jnp.asarray(tapes), jnp.zeros(NUM_TAPES, jnp.int32), jnp.zeros((), bool))


def sample_problem(key: jax.Array, num_digits, width: int) -> State:
  """A uniformly random problem with num_digits digits per operand (leading zeros allowed). Jittable;
  num_digits may be traced, width is static."""
  digits = jax.random.randint(key, (2, width), 0, 10, jnp.int32)
  inputs = jnp.where(jnp.arange(width) < num_digits, digits, EMPTY)
  tapes = jnp.concatenate([inputs, jnp.full((2, width), EMPTY, jnp.int32)])
  return State(tapes, jnp.zeros(NUM_TAPES, jnp.int32), jnp.zeros((), bool))


def symbols(state: State) -> jax.Array:
  """[4] the symbol under each head."""
  return state.tapes[jnp.arange(NUM_TAPES), state.heads]


def observe(state: State) -> jax.Array:
  """[44] float32: the four symbols under the heads, one-hot."""
  return jax.nn.one_hot(symbols(state), NUM_SYMBOLS, dtype=jnp.float32).reshape(-1)


def observed_symbols(obs: jax.Array) -> jax.Array:
  """[4] int32 symbols back from an observation."""
  return jnp.argmax(obs.reshape(NUM_TAPES, NUM_SYMBOLS), axis=-1).astype(jnp.int32)


def step(state: State, action: jax.Array) -> State:
  """Applies action = (kind, tape, arg); an invalid action only sets failed."""
  kind, tape, arg = action[0], action[1], action[2]
  width = state.tapes.shape[1]
  tape_index = jnp.clip(tape, 0, NUM_TAPES - 1)
  head = state.heads[tape_index]
  new_head = head + jnp.where(arg == LEFT, 1, -1)
  in_range = (kind >= 0) & (kind <= 1) & (tape >= 0) & (tape < NUM_TAPES) & (arg >= 0) & (arg <= 9)
  move_ok = (arg <= RIGHT) & (new_head >= 0) & (new_head < width)
  ok = in_range & jnp.where(kind == MOVE, move_ok, True)
  written = jnp.where(ok & (kind == WRITE), arg, state.tapes[tape_index, head])  # O(1), not O(width)
  return State(
      tapes=state.tapes.at[tape_index, head].set(written),
      heads=state.heads.at[tape_index].set(jnp.where(ok & (kind == MOVE), new_head, head)),
      failed=state.failed | ~ok)


def result(state: State) -> str:
  """The out tape from column 0 up to the first EMPTY, most significant digit first (host side)."""
  out = np.asarray(state.tapes[OUT])
  end = int(np.argmax(out == EMPTY)) if (out == EMPTY).any() else len(out)
  return "".join(str(d) for d in out[:end][::-1])


def oracle_step_budget(num_digits: int) -> int:
  """Elementary steps the oracle needs at most: 8 per column plus the final carry column."""
  return 8 * (num_digits + 1)


def decimal_sum(a: str, b: str) -> str:
  """a + b for decimal strings of any length, without leading zeros (Python's int() stops at 4300 digits)."""
  digits, carry = [], 0
  for d1, d2 in zip(reversed(a.rjust(len(b), "0")), reversed(b.rjust(len(a), "0"))):
    carry, digit = divmod(int(d1) + int(d2) + carry, 10)
    digits.append(str(digit))
  return (("1" if carry else "") + "".join(reversed(digits))).lstrip("0") or "0"


def is_correct(result_digits: str, a: str, b: str) -> bool:
  """Whether a result string equals a + b as an integer (leading zeros allowed; empty is wrong)."""
  return result_digits.isdigit() and (result_digits.lstrip("0") or "0") == decimal_sum(a, b)
