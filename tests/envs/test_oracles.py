"""The supervisors solve their environments at every length through the jitted executor, and their
demonstrations' stacks follow the call-stack semantics."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest

from php_jax import demos, executor
from php_jax.envs import addition as add
from php_jax.envs import addition_task, datasets, nanocraft_task, tasks
from php_jax.envs import nanocraft as nc

ADDITION = tasks.get("addition")
NANOCRAFT = tasks.get("nanocraft")


def _run(task, states, max_steps, record=True):
  batch = jax.tree.leaves(states)[0].shape[0]
  return executor.rollout_batch(task.oracle, task.spec, task.env, states,
                                jax.random.split(jax.random.key(0), batch), max_steps, record)


def _addition_cases(num_digits, count, rng):
  cases = [("9" * num_digits, "0" * (num_digits - 1) + "1"), ("9" * num_digits, "9" * num_digits),
           ("0" * num_digits, "0" * num_digits)]
  cases += [tuple("".join(map(str, rng.integers(0, 10, num_digits))) for _ in range(2))
            for _ in range(count)]
  return cases


def _check_addition(cases):
  max_digits = max(len(a) for a, _ in cases)
  rollouts = _run(ADDITION, addition_task.make_states(cases), add.oracle_step_budget(max_digits), record=False)
  assert np.all(rollouts.terminated) and np.all(rollouts.valid)
  for i, (a, b) in enumerate(cases):
    assert add.is_correct(add.result(jax.tree.map(lambda x: x[i], rollouts.final_state)), a, b)


@pytest.mark.parametrize("num_digits", list(range(1, 11)) + [100])
def test_addition_oracle_solves_every_length(num_digits):
  _check_addition(_addition_cases(num_digits, 20, np.random.default_rng(num_digits)))


def test_addition_oracle_solves_1000_digits():
  _check_addition(_addition_cases(1000, 3, np.random.default_rng(1000)))


@pytest.mark.slow
def test_addition_oracle_solves_10000_digits():
  _check_addition(_addition_cases(10_000, 2, np.random.default_rng(10_000)))


@pytest.mark.parametrize("place_prob", [0.0, 0.5, 1.0])
def test_nanocraft_oracle_solves_all_100_specs(place_prob):
  key = jax.random.key(int(place_prob * 10))
  grids = jax.vmap(nc.perimeter)(jnp.asarray(nc.SPECS))
  grids = grids & jax.random.bernoulli(key, place_prob, grids.shape)
  states = nc.State(grids, jnp.zeros((100, 2), jnp.int32), jnp.asarray(nc.SPECS), jnp.zeros(100, bool))
  rollouts = _run(NANOCRAFT, states, nc.ORACLE_STEP_BUDGET, record=False)
  assert np.all(rollouts.terminated) and np.all(rollouts.valid)
  assert np.all(jax.vmap(nc.solved)(rollouts.final_state))


def test_demonstration_stacks_follow_the_semantics():
  for task, states, budget in [
      (ADDITION, addition_task.make_states(addition_task.training_problems(seed=0)), add.oracle_step_budget(10)),
      (NANOCRAFT, nanocraft_task.make_states(nanocraft_task.random_problems(0, 64)), nc.ORACLE_STEP_BUDGET)]:
    batch = datasets.oracle_demonstrations(task, states, num_strong=1000, max_steps=budget)
    demos.validate(batch, task.spec)  # raises on any broken stack
    procs, taus, length = np.asarray(batch.procedures), np.asarray(batch.counters), np.asarray(batch.length)
    used = np.arange(procs.shape[1])[None, :] < length[:, None]
    assert np.all(procs[:, :, 0][used] == 0) and np.all(taus[:, 0] == 0)  # one root; pushes start at 0
    for b in range(len(length)):
      steps = slice(0, length[b])
      lowest = taus[b, steps, -1]
      # Each step the lowest frame either continues (τ + 1) or is a fresh push (τ = 0).
      assert np.all((lowest[1:] == lowest[:-1] + 1) | (lowest[1:] == 0))
      assert np.all(procs[b, length[b]:] == demos.UNKNOWN)


def test_nanocraft_demonstration_matches_the_paper_program():
  states = jax.tree.map(lambda x: x[None], nc.make_problem(2, 1, 3, 2, preplaced=[[1, 3]]))
  batch = datasets.oracle_demonstrations(NANOCRAFT, states, 1, nc.ORACLE_STEP_BUDGET)
  n = int(batch.length[0])
  actions = [nc.ACTION_NAMES[a] for a in np.asarray(batch.actions[0, :n, 0])]
  # moves_r ×2, moves_d ×1, builds_r ×2 (second cell pre-placed? no: [1,3] is the first build cell).
  assert actions[:3] == ["MOVE_RIGHT", "MOVE_RIGHT", "MOVE_DOWN"]
  assert actions[3:6] == ["MOVE_RIGHT", "MOVE_RIGHT", "PLACE_BLOCK"]  # (1,3) full → return; (1,4) empty
  level1 = [NANOCRAFT.spec.levels[1][p] for p in np.asarray(batch.procedures[0, :n, 1])]
  assert level1[0] == "moves_r" and level1[2] == "moves_d" and level1[-1] == "builds_u"


def test_addition_data_set_constraints():
  problems = addition_task.training_problems(seed=3)
  assert len(problems) == 160
  for n in range(1, 11):
    assert sum(len(a) == n and len(b) == n for a, b in problems) == 16
  assert len(set().union(*(addition_task.column_triples(a, b) for a, b in problems))) == 200
  assert problems == addition_task.training_problems(seed=3)
  assert problems != addition_task.training_problems(seed=4)


@pytest.mark.parametrize("digits", [2, 3, 5])
def test_covering_addition_problems_cover_every_column(digits):
  problems = addition_task.covering_problems(seed=digits, digits=digits)
  assert all(len(a) == len(b) == digits for a, b in problems)
  assert len(set().union(*(addition_task.column_triples(a, b) for a, b in problems))) == 200
  assert len(problems) <= 1.2 * 200 / (digits - 1)  # few problems: mostly new columns above the lowest
  assert problems == addition_task.covering_problems(seed=digits, digits=digits)
  with pytest.raises(ValueError, match="at least 2"):
    addition_task.covering_problems(seed=0, digits=1)


def test_column_triples():
  assert addition_task.column_triples("19", "05") == {(9, 5, 0), (1, 0, 1)}


@pytest.mark.parametrize("corrupt, message", [
    (lambda p, t, a: t.__setitem__((0, 3, 2), t[0, 3, 2] + 2), "step 3: level 2 goes from"),
    (lambda p, t, a: p.__setitem__((1, 2, 1), 7), "step 2: procedure id 7 at level 1 is unknown"),
    (lambda p, t, a: t.__setitem__((0, 0, 1), 1), "step 0: counters must start at 0"),
    (lambda p, t, a: a.__setitem__((1, 0, 0), 5), "demonstration 1, step 0: action factor 0 = 5"),
])
def test_validate_rejects_broken_annotations(corrupt, message):
  states = addition_task.make_states([("19", "25"), ("7", "8")])
  batch = datasets.oracle_demonstrations(ADDITION, states, 2, add.oracle_step_budget(2))
  procs, taus, actions = (np.array(batch.procedures), np.array(batch.counters), np.array(batch.actions))
  corrupt(procs, taus, actions)
  bad = batch._replace(procedures=procs, counters=taus, actions=actions)
  with pytest.raises(ValueError, match=message):
    demos.validate(bad, ADDITION.spec)


def test_validate_rejects_lengths_over_capacity():
  states = addition_task.make_states([("1", "2")])
  batch = datasets.oracle_demonstrations(ADDITION, states, 1, add.oracle_step_budget(1))
  with pytest.raises(ValueError, match="length 99 is outside"):
    demos.validate(batch._replace(length=jnp.array([99])), ADDITION.spec)
