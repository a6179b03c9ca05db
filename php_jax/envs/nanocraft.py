"""NanoCraft on a 6×6 grid (paper §5.1), as pure jittable state transitions.

The agent starts at row 0, column 0 and must complete the perimeter of a w × h building whose top-left cell
is (row y, column x); each perimeter cell may be pre-placed. Observation: [5] float32 = (agent's cell full,
h, w, x, y). Elementary action: int32 [1] in MOVE_RIGHT, MOVE_DOWN, MOVE_LEFT, MOVE_UP, PLACE_BLOCK. Moving off
the grid or placing on a full cell marks the episode failed and changes nothing else.
"""
from __future__ import annotations

import itertools

import jax
import jax.numpy as jnp
import numpy as np
from flax import struct

GRID = 6
MOVE_RIGHT, MOVE_DOWN, MOVE_LEFT, MOVE_UP, PLACE_BLOCK = range(5)
ACTION_SIZES = (5,)
OBS_DIM = 5
ACTION_NAMES = ("MOVE_RIGHT", "MOVE_DOWN", "MOVE_LEFT", "MOVE_UP", "PLACE_BLOCK")
_DELTAS = np.array([[0, 1], [1, 0], [0, -1], [-1, 0], [0, 0]], np.int32)  # (row, column)
# Every valid (x, y, w, h): x, y ≥ 1, w, h ≥ 2, x + w ≤ 6, y + h ≤ 6. There are 100.
SPECS = np.array([(x, y, w, h) for x, y in itertools.product(range(1, GRID - 1), repeat=2)
                  for w in range(2, GRID - x + 1) for h in range(2, GRID - y + 1)], np.int32)


@struct.dataclass
class State:
  """grid: [6, 6] bool full cells; pos: [2] int32 (row, column); spec: [4] int32 (x, y, w, h); failed: []."""
  grid: jax.Array
  pos: jax.Array
  spec: jax.Array
  failed: jax.Array


def perimeter(spec: jax.Array) -> jax.Array:
  """[6, 6] bool: the target building's perimeter for spec = (x, y, w, h). Jittable."""
  x, y, w, h = spec[0], spec[1], spec[2], spec[3]
  rows, cols = jnp.arange(GRID)[:, None], jnp.arange(GRID)[None, :]
  inside = (rows >= y) & (rows < y + h) & (cols >= x) & (cols < x + w)
  border = (rows == y) | (rows == y + h - 1) | (cols == x) | (cols == x + w - 1)
  return inside & border


def check_spec(x: int, y: int, w: int, h: int) -> None:
  """Raises ValueError unless the building fits the grid's rules."""
  if not (x >= 1 and y >= 1 and w >= 2 and h >= 2 and x + w <= GRID and y + h <= GRID):
    raise ValueError(f"building x={x}, y={y}, w={w}, h={h} does not fit: need x, y ≥ 1, w, h ≥ 2, "
                     f"x + w ≤ {GRID}, y + h ≤ {GRID}")


def make_problem(x: int, y: int, w: int, h: int, preplaced=()) -> State:
  """The start state for a building and its pre-placed [row, column] cells (each on the perimeter). Raises
  ValueError naming a field that is not an integer (bool is not) or a building or cell that does not fit."""
  for name, value in zip("xywh", (x, y, w, h)):
    if isinstance(value, (bool, np.bool_)) or not isinstance(value, (int, np.integer)):
      raise ValueError(f"{name} must be an integer; got {value!r}")
  check_spec(x, y, w, h)
  spec = np.array([x, y, w, h], np.int32)
  target = np.asarray(perimeter(jnp.asarray(spec)))
  grid = np.zeros((GRID, GRID), bool)
  for cell in preplaced:
    row, col = cell
    if not (0 <= row < GRID and 0 <= col < GRID and target[row, col]):
      raise ValueError(f"pre-placed cell [{row}, {col}] is not on the building's perimeter")
    grid[row, col] = True
  return State(jnp.asarray(grid), jnp.zeros(2, jnp.int32), jnp.asarray(spec), jnp.zeros((), bool))


def sample_problem(key: jax.Array, place_prob: float = 0.5) -> State:
  """A building drawn uniformly from the 100 specs, each perimeter cell pre-placed with place_prob."""
  spec_key, cell_key = jax.random.split(key)
  spec = jnp.asarray(SPECS)[jax.random.randint(spec_key, (), 0, len(SPECS))]
  grid = perimeter(spec) & jax.random.bernoulli(cell_key, place_prob, (GRID, GRID))
  return State(grid, jnp.zeros(2, jnp.int32), spec, jnp.zeros((), bool))


def observe(state: State) -> jax.Array:
  """[5] float32: (agent's cell full, h, w, x, y)."""
  x, y, w, h = state.spec[0], state.spec[1], state.spec[2], state.spec[3]
  full = state.grid[state.pos[0], state.pos[1]]
  return jnp.stack([full, h, w, x, y]).astype(jnp.float32)


def step(state: State, action: jax.Array) -> State:
  """Applies action [1]; an invalid action only sets failed."""
  a = action[0]
  known = (a >= 0) & (a <= PLACE_BLOCK)
  new_pos = state.pos + jnp.asarray(_DELTAS)[jnp.clip(a, 0, PLACE_BLOCK)]
  on_grid = jnp.all((new_pos >= 0) & (new_pos < GRID))
  cell_full = state.grid[state.pos[0], state.pos[1]]
  place = a == PLACE_BLOCK
  ok = known & jnp.where(place, ~cell_full, on_grid)
  return State(
      grid=jnp.where(ok & place, state.grid.at[state.pos[0], state.pos[1]].set(True), state.grid),
      pos=jnp.where(ok & ~place, new_pos, state.pos),
      spec=state.spec,
      failed=state.failed | ~ok)


def solved(state: State) -> jax.Array:
  """[] bool: the grid is exactly the pre-placed blocks plus the whole perimeter."""
  return jnp.all(state.grid == perimeter(state.spec))


ORACLE_STEP_BUDGET = 64  # the oracle needs at most x + y + 4 (w - 1 + h - 1) ≤ 40 steps.
