"""Environment transitions: each action's effect and every kind of invalid action."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from php_jax.envs import addition as add
from php_jax.envs import nanocraft as nc


def _act(*a):
  return jnp.array(a, jnp.int32)


def test_addition_layout_and_observation():
  s = add.make_problem("120", "034")
  assert s.tapes.shape == (4, 5)
  np.testing.assert_array_equal(s.tapes[add.IN1], [0, 2, 1, add.EMPTY, add.EMPTY])  # column 0 least significant
  np.testing.assert_array_equal(s.tapes[add.IN2], [4, 3, 0, add.EMPTY, add.EMPTY])
  assert np.all(s.tapes[add.CARRY] == add.EMPTY) and np.all(s.tapes[add.OUT] == add.EMPTY)
  obs = add.observe(s)
  assert obs.shape == (44,) and obs.sum() == 4
  np.testing.assert_array_equal(add.observed_symbols(obs), [0, 4, add.EMPTY, add.EMPTY])


def test_addition_move_and_write_effects():
  s = add.make_problem("12", "34")
  s = add.step(s, _act(add.MOVE, add.IN1, add.LEFT))
  assert s.heads.tolist() == [1, 0, 0, 0] and not s.failed
  assert add.observed_symbols(add.observe(s))[add.IN1] == 1
  s = add.step(s, _act(add.MOVE, add.IN1, add.RIGHT))
  assert s.heads.tolist() == [0, 0, 0, 0]
  s = add.step(s, _act(add.WRITE, add.OUT, 7))
  assert int(s.tapes[add.OUT, 0]) == 7 and not s.failed
  s = add.step(s, _act(add.WRITE, add.IN2, 0))  # writing on an input tape is allowed
  assert int(s.tapes[add.IN2, 0]) == 0 and not s.failed


@pytest.mark.parametrize("action", [
    (add.MOVE, add.OUT, add.RIGHT),   # off the tape at column 0
    (add.MOVE, add.IN1, 5),           # MOVE with an arg other than LEFT / RIGHT
    (2, add.IN1, 0), (add.WRITE, 4, 1), (add.WRITE, add.OUT, 10), (add.WRITE, add.OUT, -1),
])
def test_addition_invalid_actions_fail_and_change_nothing(action):
  s = add.make_problem("5", "5")
  after = add.step(s, _act(*action))
  assert bool(after.failed)
  np.testing.assert_array_equal(after.tapes, s.tapes)
  np.testing.assert_array_equal(after.heads, s.heads)


def test_addition_move_off_the_far_end_fails():
  s = add.make_problem("5", "5")  # width 3
  for _ in range(2):
    s = add.step(s, _act(add.MOVE, add.CARRY, add.LEFT))
  assert not s.failed
  assert add.step(s, _act(add.MOVE, add.CARRY, add.LEFT)).failed


def test_addition_rejects_bad_problems():
  for a, b in [("12", "3"), ("", ""), ("1a", "22"), ("٣", "1")]:
    with pytest.raises(ValueError):
      add.make_problem(a, b)
  with pytest.raises(ValueError, match="too small"):
    add.make_problem("12", "34", width=3)


def test_addition_sample_problem_is_jittable_and_respects_length():
  states = jax.jit(jax.vmap(lambda k, n: add.sample_problem(k, n, 12)))(
      jax.random.split(jax.random.key(0), 3), jnp.array([1, 5, 10]))
  for i, n in enumerate([1, 5, 10]):
    digits = np.asarray(states.tapes[i, :2])
    assert np.all(digits[:, :n] < 10) and np.all(digits[:, n:] == add.EMPTY)


def test_addition_result_reads_out_tape():
  s = add.make_problem("99", "01")
  tapes = s.tapes.at[add.OUT, :3].set(jnp.array([0, 0, 1]))
  assert add.result(s.replace(tapes=tapes)) == "100"
  assert add.result(s) == ""


def test_nanocraft_specs_and_perimeter():
  assert len(nc.SPECS) == 100 and len({tuple(s) for s in nc.SPECS}) == 100
  grid = np.asarray(nc.perimeter(jnp.array([1, 2, 4, 3])))
  assert grid.sum() == 2 * 4 + 2 * 3 - 4
  assert grid[2, 1] and grid[2, 4] and grid[4, 4] and not grid[3, 2] and not grid[1, 1]


def test_nanocraft_moves_place_and_observation():
  s = nc.make_problem(1, 1, 2, 3, preplaced=[[1, 1]])
  np.testing.assert_array_equal(nc.observe(s), [0, 3, 2, 1, 1])
  s = nc.step(s, _act(nc.MOVE_RIGHT))
  s = nc.step(s, _act(nc.MOVE_DOWN))
  assert s.pos.tolist() == [1, 1] and nc.observe(s)[0] == 1
  s = nc.step(s, _act(nc.MOVE_RIGHT))
  s = nc.step(s, _act(nc.PLACE_BLOCK))
  assert bool(s.grid[1, 2]) and not s.failed and nc.observe(s)[0] == 1
  s = nc.step(s, _act(nc.MOVE_LEFT))
  s = nc.step(s, _act(nc.MOVE_UP))
  assert s.pos.tolist() == [0, 1] and not s.failed


@pytest.mark.parametrize("moves", [[nc.MOVE_UP], [nc.MOVE_LEFT], [nc.MOVE_RIGHT] * 6, [nc.MOVE_DOWN] * 6,
                                   [nc.PLACE_BLOCK, nc.PLACE_BLOCK], [7], [-1]])
def test_nanocraft_invalid_actions_fail_and_change_nothing(moves):
  s = nc.make_problem(1, 1, 2, 2)
  for m in moves[:-1]:
    s = nc.step(s, _act(m))
  assert not s.failed
  after = nc.step(s, _act(moves[-1]))
  assert bool(after.failed)
  np.testing.assert_array_equal(after.grid, s.grid)
  np.testing.assert_array_equal(after.pos, s.pos)


def test_nanocraft_rejects_bad_problems():
  with pytest.raises(ValueError, match="does not fit"):
    nc.make_problem(0, 1, 2, 2)
  with pytest.raises(ValueError, match="does not fit"):
    nc.make_problem(3, 1, 4, 2)
  with pytest.raises(ValueError, match="not on the building's perimeter"):
    nc.make_problem(1, 1, 3, 3, preplaced=[[2, 2]])


def test_nanocraft_sample_problem_places_only_perimeter_cells():
  states = jax.jit(jax.vmap(nc.sample_problem))(jax.random.split(jax.random.key(3), 200))
  target = jax.vmap(nc.perimeter)(states.spec)
  assert not np.any(np.asarray(states.grid) & ~np.asarray(target))
  fraction = np.asarray(states.grid).sum() / np.asarray(target).sum()
  assert 0.4 < fraction < 0.6
  specs = {tuple(s) for s in np.asarray(states.spec)}
  assert specs <= {tuple(s) for s in nc.SPECS} and len(specs) > 50


def test_decimal_sum_and_correctness_rule():
  assert add.decimal_sum("999", "001") == "1000" and add.decimal_sum("00", "00") == "0"
  assert add.decimal_sum("5" * 5000, "5" * 5000) == "1" + "1" * 4999 + "0"
  assert add.is_correct("0100", "099", "001") and add.is_correct("00", "00", "00")
  assert not add.is_correct("", "0", "0") and not add.is_correct("101", "099", "001")
  assert add.decimal_sum("9999999999", "0000000001") == "10000000000"
