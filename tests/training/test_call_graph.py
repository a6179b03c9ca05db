"""Call graphs: read from the annotation, checked against every demonstration, enforced by the networks (an
operation outside the graph has probability 0 and the others renormalise), and saved with the model."""
import dataclasses
import json

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx

from php_jax.data import demo_files
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import datasets, tasks
from php_jax.hierarchy import HierarchySpec
from php_jax.inference import stack_lattice
from php_jax.model import PHPHierarchy, PHPLevel
from php_jax.training import call_graph, checkpoint, networks, objective, run, storage
from php_jax.training.config import TrainConfig
SPEC = HierarchySpec("tiny", (("root",), ("a", "b"), ("x", "y", "z")), (2, 3), 3)
NANOCRAFT = tasks.get("nanocraft")


def _demos(procedures, actions, strong) -> Demonstration:
  """Demonstrations [B] of procedures [B, T, 3] and actions [B, T, 2] (counters, observations do not matter)."""
  procedures = np.asarray(procedures, np.int32)
  num, steps = procedures.shape[:2]
  return Demonstration(np.zeros((num, steps + 1, 3), np.float32), np.asarray(actions, np.int32), procedures,
                       np.where(procedures == UNKNOWN, UNKNOWN, 0), np.full(num, steps, np.int32),
                       np.asarray(strong, bool))


def test_the_annotated_call_graph_keeps_the_operations_shown_and_leaves_the_unseen_free():
  demos = _demos([[[0, 0, 0], [0, 1, 1], [0, 1, UNKNOWN]],   # a calls x, b calls y
                  [[0, 0, 2], [0, 1, 2], [0, 0, 2]]],        # weak: not evidence
                 [[[0, 0], [1, 1], [1, 2]], [[1, 2], [1, 2], [1, 2]]], strong=[True, False])
  root, level1, lowest = call_graph.from_annotation(demos, SPEC)
  # The root calls both a and b: unrestricted. z is never shown being called: anyone may call it.
  assert root is None and level1 == ((True, False, True), (False, True, True))
  # x takes (0, 0) and y (1, 1): per factor only those values, but value 2 of the second factor, which no
  # procedure is shown taking, is free; z is never shown: unrestricted.
  assert lowest == ((True, False, True, False, True), (False, True, False, True, True), (True,) * 5)
  assert call_graph.from_annotation(demos._replace(strong=np.zeros(2, bool)), SPEC) == (None, None, None)
  assert call_graph.from_annotation(demos, SPEC, actions=False) == (root, level1, None)
  assert call_graph.resolve("all", demos, SPEC) == (None, None, None)


def test_a_demonstration_outside_the_graph_is_refused_naming_demonstration_and_step():
  graph = (None, ((True, False, False), (False, True, False)), ((True, False, True, True, True),) * 3)
  fits = _demos([[[0, UNKNOWN, 0], [0, 1, UNKNOWN], [0, UNKNOWN, UNKNOWN]]], [[[0, 0]] * 3], [True])
  call_graph.check(fits, SPEC, graph)
  call_graph.check(fits._replace(strong=np.zeros(1, bool)), SPEC, graph)
  bad = _demos([[[0, 0, 0], [0, 1, UNKNOWN]], [[0, UNKNOWN, 0], [0, 1, 0]]], [[[0, 0]] * 2] * 2, [True, True])
  with pytest.raises(ValueError, match="demonstration 1, step 1: .*level 2"):
    call_graph.check(bad, SPEC, graph)
  with pytest.raises(ValueError, match="demonstration 0, step 0"):
    call_graph.check(_demos([[[0, UNKNOWN, 2]]], [[[0, 0]]], [True]), SPEC, graph)  # nobody may call z
  with pytest.raises(ValueError, match="demonstration 0, step 1"):  # no procedure takes action value 1 first
    call_graph.check(_demos([[[UNKNOWN] * 3] * 2], [[[0, 0], [1, 0]]], [False]), SPEC, graph)


def test_operations_outside_the_graph_get_probability_zero_and_the_others_renormalise():
  allowed_ops = ((True, False, True, False, True), (False, True, True, True, True))
  free = PHPLevel(2, 3, (2, 3), (8,), rngs=nnx.Rngs(0))
  masked = PHPLevel(2, 3, (2, 3), (8,), allowed_ops=allowed_ops, rngs=nnx.Rngs(0))
  obs, tau = jax.random.normal(jax.random.key(1), (4, 3)), jnp.arange(3.0)
  ops = jnp.array([[0, 0], [1, 1], [0, 2], [1, 0]])

  @nnx.jit
  def evaluate(free, masked):
    def finite_sum(level):  # −inf where an operation is not allowed: its gradient must still be finite
      return jnp.sum(jnp.where(jnp.isfinite(lp := level.log_op(obs, tau, ops)), lp, 0.0))
    return (free.op_log_probs(obs, tau), masked.op_log_probs(obs, tau), masked.log_op(obs, tau, ops),
            nnx.grad(finite_sum)(masked))
  free_lps, masked_lps, log_op, grads = evaluate(free, masked)
  total = 0.0
  for f, (start, size) in enumerate(((0, 2), (2, 3))):
    allowed = np.asarray(allowed_ops)[None, :, None, start:start + size]            # [1, K, 1, size]
    free_lp, masked_lp = free_lps[f], masked_lps[f]                                  # [N, K, M, size]
    expected = free_lp - jax.nn.logsumexp(jnp.where(allowed, free_lp, -jnp.inf), axis=-1, keepdims=True)
    np.testing.assert_allclose(masked_lp, np.where(allowed, expected, -np.inf), rtol=1e-5, atol=1e-5)
    total = total + np.take_along_axis(np.asarray(masked_lp), np.asarray(ops)[:, None, None, f:f + 1], axis=-1)[..., 0]
  np.testing.assert_allclose(log_op, total, rtol=1e-5)
  assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))
  with pytest.raises(ValueError, match=r"allowed_ops must be \[2\]\[5\]"):
    PHPLevel(2, 3, (2, 3), (8,), allowed_ops=((True,) * 5,), rngs=nnx.Rngs(0))


def test_nanocrafts_annotation_shows_the_supervisors_call_graph():
  graph = call_graph.resolve("operations", datasets.training_demos(NANOCRAFT, 1, 4, 4), NANOCRAFT.spec)
  assert graph[:2] == (None, tuple(tuple(i == j for j in range(6)) for i in range(6)))  # builds_r: build_r, ...
  # MOVE_RIGHT, MOVE_DOWN, MOVE_LEFT, MOVE_UP, PLACE_BLOCK: move_r and move_d only move; build_X moves or places.
  assert np.asarray(graph[2]).astype(int).tolist() == [[1, 0, 0, 0, 0], [0, 1, 0, 0, 0], [1, 0, 0, 0, 1],
                                                        [0, 1, 0, 0, 1], [0, 0, 1, 0, 1], [0, 0, 0, 1, 1]]


def test_the_stack_lattice_of_a_graph_is_the_free_one_renormalised_over_allowed_calls():
  graph = (None, ((True, False, True), (False, True, False)), None)
  config, capacity = TrainConfig(hidden=(8,), seed=1), (4, 3, 2)
  free, masked = networks.make_hierarchy(SPEC, config), networks.make_hierarchy(SPEC, config, graph)
  key_obs, key_act = jax.random.split(jax.random.key(2))
  # Three weak demonstrations, and one annotated with a call outside the graph (b calls x): impossible.
  procs, taus = np.full((4, 4, 3), UNKNOWN), np.full((4, 4, 3), UNKNOWN)
  procs[3, 0], taus[3, 0] = (0, 1, 0), (0, 0, 0)
  batch = Demonstration(jax.random.normal(key_obs, (4, 5, 3)), jax.random.randint(key_act, (4, 4, 2), 0, jnp.array([2, 3])),
                        procs, taus, np.array([4, 3, 2, 1]), np.array([False, False, False, True]))

  def renormalised(obs, act, n):
    inputs = objective.stack_inputs(free, capacity, obs, act, n)
    allowed = np.asarray(graph[1])[None, :, None, :]
    log_call = inputs.log_call[1] - jax.nn.logsumexp(jnp.where(allowed, inputs.log_call[1], -jnp.inf), -1, keepdims=True)
    return stack_lattice.log_likelihood(inputs._replace(log_call=(inputs.log_call[0], jnp.where(allowed, log_call,
                                                                                                 -jnp.inf))))
  ours, expected = jax.jit(lambda: (objective.stack_log_likelihoods(masked, batch, capacity),
                                    jax.vmap(renormalised)(batch.observations[:3], batch.actions[:3],
                                                           batch.length[:3])))()
  np.testing.assert_allclose(ours[:3], expected, rtol=1e-5)
  assert ours[3] == -np.inf


def test_the_call_graph_is_saved_with_the_model(tmp_path):
  graph = (None, tuple(tuple(i == j for j in range(6)) for i in range(6)), ((True, False, False, False, True),) * 6)
  hierarchy = PHPHierarchy(NANOCRAFT.spec, hidden=(4,), allowed_ops=graph, rngs=nnx.Rngs(0))
  checkpoint.save_hierarchy(str(tmp_path), "nanocraft", hierarchy, (4,))
  _, loaded = checkpoint.load_policy(str(tmp_path))
  assert [level.allowed_ops for level in loaded.levels] == list(graph)
  path = tmp_path / checkpoint.ARCHITECTURE_FILE
  architecture = json.loads(path.read_text())
  architecture["allowed_ops"][1] = [[True] * 5] * 6
  path.write_text(json.dumps(architecture))
  with pytest.raises(checkpoint.CheckpointError, match="model.json: edited or corrupt"):  # an edited model.json
    checkpoint.load_policy(str(tmp_path))
  del architecture["sha256"]  # signed anew: the graph's own check refuses it
  path.write_text(json.dumps(storage.signed(architecture)))
  with pytest.raises(checkpoint.CheckpointError, match="malformed allowed_ops"):
    checkpoint.load_policy(str(tmp_path))


def test_what_procedures_observe_is_saved_with_the_model(tmp_path):
  observes = (None, None, tuple((0, 1) if k % 2 else () for k in range(len(NANOCRAFT.spec.levels[2]))))
  spec = dataclasses.replace(NANOCRAFT.spec, observes=observes)
  hierarchy = PHPHierarchy(spec, hidden=(4,), rngs=nnx.Rngs(0))
  checkpoint.save_hierarchy(str(tmp_path), "nanocraft", hierarchy, (4,))
  _, loaded = checkpoint.load_policy(str(tmp_path))
  assert loaded.spec.observes == observes and [level.observes for level in loaded.levels] == list(observes)
  obs, tau = jnp.ones((2, spec.obs_dim)), jnp.arange(3.0)
  np.testing.assert_array_equal(loaded.levels[2].termination_logits(obs, tau),
                                hierarchy.levels[2].termination_logits(obs, tau))


def _hierarchy_file(tmp_path, calls) -> str:
  path = tmp_path / "tiny.json"
  path.write_text(json.dumps({"levels": [list(level) for level in SPEC.levels], "action_sizes": [2, 3],
                              "calls": calls}))
  return str(path)


def test_a_declared_call_graph_is_read_from_the_hierarchy_file_and_bounds_the_annotated_one(tmp_path):
  path = _hierarchy_file(tmp_path, [None, {"a": ["x"], "b": ["y", "z"]}, {"z": [[1], [0, 2]]}])
  spec = dataclasses.replace(demo_files.read_hierarchy(path).spec, obs_dim=3)
  declared = (None, ((True, False, False), (False, True, True)),
              ((True,) * 5, (True,) * 5, (False, True, True, False, True)))
  assert spec.allowed_ops == declared
  demos = _demos([[[0, 0, 0], [0, 1, 2]]], [[[0, 0], [1, 2]]], strong=[True])  # a calls x; b calls z
  assert call_graph.resolve("all", demos, spec) == declared
  # The annotation shows z taking (1, 2), and no procedure taking value 1 of the second factor (left free):
  # within the declared graph, z may take (1, 2) alone; x (declared free) what the annotation leaves it.
  assert call_graph.resolve("operations", demos, spec)[2] == (
      (True, False, True, True, False), (True,) * 5, (False, True, False, False, True))
  outside = _demos([[[0, 0, 1]]], [[[0, 0]]], strong=[True])  # a calls y, which the file forbids
  with pytest.raises(ValueError, match="demonstration 0, step 0: no chain of calls that the call graph allows"):
    call_graph.resolve("all", outside, spec)


@pytest.mark.parametrize("calls, message", [
    ([None, None], r'"calls" must give one object or null per level, root first \(3\)'),
    ([None, {"c": ["x"]}, None], "level 1 has no procedure 'c'"),
    ([None, {"a": ["w"]}, None], r"""'a' must list procedures of level 2 \(x, y, z\)"""),
    ([None, None, {"x": [[0], [3]]}], "'x' must list, per action factor, the values it may take"),
    ([None, None, {"x": [0, 1]}], "'x' must list, per action factor"),  # two factors: a list per factor
])
def test_bad_declared_call_graphs_are_refused_naming_the_file(tmp_path, calls, message):
  path = _hierarchy_file(tmp_path, calls)
  with pytest.raises(demo_files.DemoFileError, match=f"^{path}: " + r'"calls"' + f".*{message}|^{path}: {message}"):
    demo_files.read_hierarchy(path)


def test_unshown_pairs_are_the_splits_the_graph_forces_that_no_annotated_demonstration_shows():
  # The annotation shows x taking (0, 0) and y (1, 1); the declared graph lets z take only (0, 0).
  demos = _demos([[[0, 0, 0], [0, 1, 1], [0, 1, 1]]] + [[[UNKNOWN] * 3] * 3] * 2,
                 [[[0, 0], [1, 1], [1, 1]], [[1, 1], [0, 0], [0, 0]], [[0, 0], [1, 1], [0, 0]]], [True, False, False])
  anything, only_00, only_11 = (True,) * 5, (True, False, True, False, False), (False, True, False, True, False)
  spec = dataclasses.replace(SPEC, allowed_ops=(None, None, (anything, anything, only_00)))
  # (1, 1) then (0, 0): no procedure may take both, and only weak demonstrations take it (1 and 2); (0, 0)
  # then (1, 1) is annotated (a split there is what the annotation shows); (0, 0) twice: x may repeat.
  assert call_graph.unshown_pairs(demos, spec, call_graph.resolve("operations", demos, spec)) == [
      call_graph.UnshownPair((1, 1), (0, 0), 2, 1)]
  # A split that the declared graph forces too is the user's choice; without a restricted lowest level, none.
  declared = dataclasses.replace(SPEC, allowed_ops=(None, None, (only_00, only_11, only_00)))
  assert call_graph.unshown_pairs(demos, declared, call_graph.resolve("operations", demos, declared)) == []
  assert call_graph.unshown_pairs(demos, SPEC, call_graph.resolve("calls", demos, SPEC)) == []


def test_a_run_warns_of_the_operations_its_few_annotated_demonstrations_lock_out():
  # NanoCraft seed 2 with 2 of 64 annotated: neither shows build_d or build_u placing a block.
  demos = datasets.training_demos(NANOCRAFT, 2, 64, 2)
  experiment = run.Experiment("nanocraft", NANOCRAFT.spec, demos, None, None, {}, NANOCRAFT.action_name,
                              numbers=tuple(range(100, 164)))
  rows = []
  gaps = run.annotation_gaps(experiment, TrainConfig(call_graph="operations"), rows.append)
  pairs = [(g["first"], g["second"]) for g in gaps["annotation_gaps"]]
  assert ([3], [4]) in pairs and ([1], [4]) in pairs  # MOVE_UP, MOVE_DOWN then PLACE_BLOCK
  assert all(g["example"] >= 100 and not demos.strong[g["example"] - 100] for g in gaps["annotation_gaps"])
  assert len(rows) == len(pairs) and "'MOVE_DOWN' then 'PLACE_BLOCK'" in " ".join(r["warning"] for r in rows)
  assert run.annotation_gaps(experiment, TrainConfig(call_graph="all"), rows.append) == {} and len(rows) == len(pairs)
  # Every demonstration annotated: the graph is the supervisor's and nothing is locked out.
  whole = dataclasses.replace(experiment, demos=datasets.training_demos(NANOCRAFT, 2, 64, 64))
  assert run.annotation_gaps(whole, TrainConfig(call_graph="operations"), rows.append) == {}
