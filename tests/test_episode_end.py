"""Demonstrations whose environment ended them (`end_given`): the return after the last action is given, not
learned, in both lattices' inputs; replay asks for every recorded action, not for the root's return; the
setting is saved with the model."""
from __future__ import annotations

import json

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax.data import views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import replay
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, RootMLP
from php_jax.training import checkpoint, objective

SPEC = HierarchySpec("ends", (("root",), ("a", "b"), ("c", "d")), (1,), 3)


def _pair(**kwargs) -> tuple[PHPHierarchy, PHPHierarchy]:
  """The same networks, learning the last return and given it."""
  return tuple(PHPHierarchy(SPEC, hidden=(8,), end_given=given, rngs=nnx.Rngs(0), **kwargs) for given in (False, True))


def _demonstrations(lengths=(4, 2), num_steps: int = 5) -> Demonstration:
  rng = np.random.default_rng(0)
  unknown = np.full((len(lengths), num_steps, SPEC.num_levels), UNKNOWN, np.int32)
  return Demonstration(rng.normal(size=(len(lengths), num_steps + 1, SPEC.obs_dim)).astype(np.float32),
                       np.zeros((len(lengths), num_steps, 1), np.int32), unknown, unknown,
                       np.array(lengths, np.int32), np.zeros(len(lengths), bool))


def test_the_last_return_is_given_in_both_lattices_and_nothing_else_changes():
  learned, given = _pair()
  demos = _demonstrations()
  for b, length in enumerate(demos.length):
    args = (jnp.asarray(demos.observations[b]), jnp.asarray(demos.actions[b]), jnp.int32(length))
    a, g = (objective.stack_inputs(h, (1, 3, 2), *args) for h in (learned, given))
    for level in range(SPEC.num_levels):
      np.testing.assert_array_equal(g.log_stop[level][length - 1], 0.0)
      keep = np.arange(5) != length - 1
      np.testing.assert_array_equal(g.log_stop[level][keep], a.log_stop[level][keep])
      np.testing.assert_array_equal(g.log_cont[level], a.log_cont[level])
    np.testing.assert_array_equal(g.log_act, a.log_act)
  view = views.device_view(views.lowest_view(demos, SPEC.num_levels))
  one = jax.tree.map(lambda x: x[0], view)
  root = RootMLP(SPEC.obs_dim, 2, (4,), rngs=nnx.Rngs(1))
  a, g = (objective.lattice_inputs(objective.LevelModel(h.levels[-1], root), one, 2) for h in (learned, given))
  np.testing.assert_array_equal(g.log_stop[int(one.length) - 1], 0.0)
  np.testing.assert_array_equal(g.log_op, a.log_op)


def test_replay_asks_for_every_action_not_the_roots_return_and_the_setting_is_saved(tmp_path):
  learned, given = _pair()
  for hierarchy in (learned, given):  # networks that never stop: the root never returns
    for level in hierarchy.levels:
      level.termination.biases[-1][...] = jnp.full_like(level.termination.biases[-1][...], -30.0)
  demos = _demonstrations()
  assert not replay.replay(learned, SPEC, demos).replayed.any()
  assert replay.replay(given, SPEC, demos).replayed.all()
  checkpoint.save_hierarchy(str(tmp_path), "ends", given, (8,))
  assert json.loads((tmp_path / checkpoint.ARCHITECTURE_FILE).read_text())["end_given"] is True
  assert checkpoint.load_policy(str(tmp_path))[1].end_given
