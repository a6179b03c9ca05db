"""Joint EG training of every level at once (--training=joint): it fits, and an interrupted run resumes to
the same result."""
import dataclasses

import jax
import numpy as np
import pytest
from flax import nnx

from php_jax.data import agreement, views
from php_jax.envs import datasets, tasks
from php_jax.training import checkpoint, joint, networks, objective, segmentation
from php_jax.training.config import (DISCOVERY_SPLIT_ROUNDS, WEAK_ONLY_ANNEALING, ConfigError, TrainConfig, prepare,
                                     resolved)

NANOCRAFT = tasks.get("nanocraft")


def test_joint_training_lowers_the_loss_and_fits_annotated_demonstrations():
  batch = datasets.training_demos(NANOCRAFT, 1, 4, 4)
  config = TrainConfig(iterations=40, learning_rate=3e-2, hidden=(16,), eval_every=20, training="joint",
                             seed=1, length_buckets=1)
  rows = []
  hierarchy, report = joint.train_joint(NANOCRAFT.spec, batch, config, log=rows.append)
  losses = [loss for _, loss in report["losses"]]
  padding = views.padding_fraction(views.length_buckets(batch, 1))  # one bucket: every shorter one padded
  assert rows[0] == {"training": "joint", "capacity": report["capacity"], "padding": round(padding, 4),
                     "unexplained": 0} and padding > 0 and report["unexplained"] == 0
  assert losses[-1] < 0.5 * losses[0]
  assert report["capacity"][1:] == [int(np.max(np.asarray(batch.counters)[..., level])) + 1 for level in (1, 2)]


def test_annealing_tempers_the_loss_from_its_start_temperature_down_to_1_at_half_the_iterations():
  temperatures = [float(objective.annealed_temperature(4.0, i, 40)) for i in (0, 10, 20, 39)]
  np.testing.assert_allclose(temperatures, [4.0, 2.5, 1.0, 1.0])
  batch = datasets.training_demos(NANOCRAFT, 1, 4, 1)
  config = TrainConfig(iterations=40, learning_rate=3e-2, hidden=(16,), eval_every=1, training="joint",
                             seed=1, length_buckets=1, anneal_temperature=4.0)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, prepare(NANOCRAFT.spec, batch, config), None)
  capacity = joint.joint_capacity(batch, NANOCRAFT.spec, config)
  [(bucket, real)] = views.demonstration_buckets(batch, 1)
  want = [float(objective.stack_loss(hierarchy, [(bucket, real)], capacity, 1.0, t)) for t in (4.0, 1.0)]
  _, report = joint.train_joint(NANOCRAFT.spec, batch, dataclasses.replace(config, strong_weight=1.0),
                                log=lambda row: None)
  losses = [loss for _, loss in report["losses"]]
  # The first update's loss is the tempered one (the actions-only demonstrations' −T log Σ P^(1/T) is lower
  # than their −log P(ξ)), and training lowers it.
  np.testing.assert_allclose(losses[0], want[0], rtol=1e-5)
  assert want[0] < want[1] and losses[-1] < 0.5 * losses[0]


def test_runs_without_annotation_train_jointly_and_anneal_by_default():
  weak, mixed = datasets.training_demos(NANOCRAFT, 1, 4, 0), datasets.training_demos(NANOCRAFT, 1, 4, 1)
  unset, joint_config = TrainConfig(), TrainConfig(training="joint")
  levelwise = TrainConfig(training="levelwise")
  mode = lambda demos, config: (lambda c: (c.training, c.anneal_temperature))(prepare(NANOCRAFT.spec, demos,
                                                                                             config))
  assert mode(weak, unset) == mode(weak, joint_config) == ("joint", WEAK_ONLY_ANNEALING) and WEAK_ONLY_ANNEALING > 1
  assert mode(mixed, unset) == ("levelwise", 1) and mode(mixed, joint_config) == ("joint", 1)
  assert mode(weak, levelwise) == ("levelwise", 1)
  assert mode(weak, dataclasses.replace(unset, strong_warmup=10)) == ("levelwise", 1)  # a level-wise setting
  assert mode(weak, dataclasses.replace(unset, call_penalty=(0, 1, 0))) == ("joint", WEAK_ONLY_ANNEALING)  # both modes'
  assert mode(mixed, dataclasses.replace(unset, anneal_temperature=2.0)) == ("joint", 2.0)
  assert mode(weak, dataclasses.replace(joint_config, anneal_temperature=1.0)) == ("joint", 1)
  flat = resolved(unset, weak, NANOCRAFT.spec, flat=True)
  assert flat.training == "levelwise"  # as flat baselines record it
  def discovery(demos, config, spec=NANOCRAFT.spec):
    settled = resolved(config, demos, spec)
    return settled.segment_iterations, settled.split_rounds
  assert discovery(weak, unset) == (unset.iterations // 2, DISCOVERY_SPLIT_ROUNDS)  # NanoCraft's actions loop
  assert discovery(mixed, unset) == discovery(weak, levelwise) == (0, 0)
  addition = tasks.get("addition")
  assert discovery(datasets.training_demos(addition, 1, 4, 0), unset, addition.spec) == (0, 0)  # no loops
  bubblesort, successors = tasks.get("bubblesort"), dataclasses.replace(unset, segment_rule="successors")
  # bubble sort's rule: the segmentation without the split search
  assert discovery(datasets.training_demos(bubblesort, 1, 4, 0), successors, bubblesort.spec) == (
      unset.iterations // 2, 0)
  assert discovery(weak, dataclasses.replace(unset, split_rounds=0)) == (unset.iterations // 2, 0)
  assert discovery(weak, dataclasses.replace(unset, segment_iterations=0)) == (0, 0)  # no segmentation, no search
  assert discovery(weak, dataclasses.replace(unset, segment_iterations=10)) == (10, DISCOVERY_SPLIT_ROUNDS)
  declared = dataclasses.replace(NANOCRAFT.spec, allowed_ops=(None, None, ((True,) * 5,) * 6))
  assert discovery(weak, unset, declared) == (0, 0)  # a declared call graph says who takes what
  assert mode(mixed, dataclasses.replace(unset, split_rounds=1)) == ("joint", 1)  # a joint-only setting
  with pytest.raises(ValueError, match="training: levelwise; this trains jointly"):
    joint.train_joint(NANOCRAFT.spec, weak, levelwise)


def test_the_first_segment_iterations_fit_the_segmentation_as_a_partial_annotation():
  weak = datasets.training_demos(NANOCRAFT, 1, 4, 0)
  config = TrainConfig(iterations=4, learning_rate=1e-2, hidden=(16,), eval_every=1, seed=1, length_buckets=1,
                             anneal_temperature=1.0, segment_iterations=2, split_rounds=0)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, prepare(NANOCRAFT.spec, weak, config), None)
  hinted = segmentation.hinted_demonstrations(weak, joint.joint_capacity(weak, NANOCRAFT.spec, config))
  # The levels the segmentation annotates take its longest calls as their capacity; the root keeps the default.
  capacity = joint.joint_capacity(weak, NANOCRAFT.spec, config, (hinted,))
  segmented = np.asarray(hinted.counters)[..., 1:].reshape(-1, 2).max(0) + 1
  assert capacity == (config.capacity, *segmented) and max(segmented) < config.capacity
  # A validation demonstration with a longer loop (its first 6 actions one move) widens level 1 for the judge.
  actions = np.asarray(weak.actions).copy()
  actions[0, :6] = actions[0, 0]
  judge = jax.tree.map(lambda x: np.asarray(x)[:1], weak._replace(actions=actions))
  assert segmentation.loop_counters(judge, segmentation.attached_actions(weak))[0, 5, 0] == 5
  _, report = joint.train_joint(NANOCRAFT.spec, weak, dataclasses.replace(config, iterations=1, segment_iterations=1),
                                log=lambda row: None, validation_demos=judge)
  assert report["capacity"] == [config.capacity, max(6, segmented[0]), segmented[1]]
  want = [float(objective.stack_loss(hierarchy, views.demonstration_buckets(d, 1), capacity, 1.0))
          for d in (hinted, weak)]
  _, report = joint.train_joint(NANOCRAFT.spec, weak, config, log=lambda row: None)
  # The first update's loss is the hinted one: −log P(hinted counters, actions) > −log P(actions).
  assert report["capacity"] == list(capacity)
  np.testing.assert_allclose(report["losses"][0][1], want[0], rtol=1e-5)
  assert want[0] > want[1] + 1 and "split_search" not in report
  cycle = np.array([0, 1, 2, 0, 2, 1])  # no value follows itself, and each is followed by two others
  unsegmented = weak._replace(actions=np.broadcast_to(cycle[np.arange(actions.shape[1]) % 6, None],
                                                      actions.shape).copy())
  for rule in segmentation.RULES:
    with pytest.raises(ConfigError, match=f"segment_iterations: the demonstrations' actions show nothing that "
                                          f"--segment_rule={rule} segments"):
      joint.train_joint(NANOCRAFT.spec, unsegmented, dataclasses.replace(config, segment_rule=rule))
  declared = dataclasses.replace(NANOCRAFT.spec, allowed_ops=(None, None, ((True,) * 5,) * 6))
  with pytest.raises(ConfigError, match="segment_iterations: needs every procedure free to take any operation"):
    joint.train_joint(declared, weak, config)
  annotated = datasets.training_demos(NANOCRAFT, 1, 4, 4)
  with pytest.raises(ConfigError, match="split_rounds: needs every procedure free to take any operation"):
    joint.train_joint(NANOCRAFT.spec, annotated, dataclasses.replace(config, segment_iterations=0, split_rounds=1,
                                                                     call_graph="calls"))


def test_the_call_penalty_costs_each_call_of_a_level_its_lambda():
  batch = datasets.training_demos(NANOCRAFT, 1, 3, 3)
  config = TrainConfig(hidden=(8,), training="joint", seed=1)
  hierarchy = networks.make_hierarchy(NANOCRAFT.spec, prepare(NANOCRAFT.spec, batch, config), None)
  capacity, penalty = joint.joint_capacity(batch, NANOCRAFT.spec, config), (0.0, 0.7, 0.2)
  plain = objective.stack_log_likelihoods(hierarchy, batch, capacity)
  penalized = objective.stack_log_likelihoods(hierarchy, batch, capacity, call_penalty=penalty)
  procedures, counters = np.asarray(batch.procedures), np.asarray(batch.counters)
  cost = [sum(penalty[level] * agreement.call_starts(procedures[b, :n], counters[b, :n], level).sum()
              for level in (1, 2)) for b, n in enumerate(np.asarray(batch.length))]
  assert min(cost) > 1  # every demonstration makes calls at both levels
  np.testing.assert_allclose(np.asarray(plain) - np.asarray(penalized), cost, rtol=1e-4)
  # Without annotation every stack pays for its calls: the likelihood falls, and falls further with a larger λ.
  weak = batch._replace(procedures=np.full_like(procedures, -1), counters=np.full_like(counters, -1),
                        strong=np.zeros_like(batch.strong))
  falls = [np.asarray(objective.stack_log_likelihoods(hierarchy, weak, capacity)
                      - objective.stack_log_likelihoods(hierarchy, weak, capacity, call_penalty=(0.0, 0.0, lam)))
           for lam in (0.1, 0.4)]
  assert np.all(0 < falls[0]) and np.all(falls[0] < falls[1])


@pytest.mark.slow
def test_interrupted_joint_training_resumes_to_the_same_result(tmp_path):
  batch = datasets.training_demos(NANOCRAFT, 2, 6, 2)
  config = TrainConfig(iterations=30, learning_rate=1e-2, hidden=(16,), eval_every=10, training="joint", seed=2)
  reference, _ = joint.train_joint(NANOCRAFT.spec, batch, config, log=lambda row: None)

  def stop_at_20(row):
    if row.get("iteration") == 20:
      raise KeyboardInterrupt
  path = str(tmp_path / checkpoint.TRAINING_DIR)
  with pytest.raises(KeyboardInterrupt):
    joint.train_joint(NANOCRAFT.spec, batch, config, log=stop_at_20, checkpoint_path=path)
  rows = []
  resumed, _ = joint.train_joint(NANOCRAFT.spec, batch, config, log=rows.append, checkpoint_path=path)
  # The checkpoint follows a row's logging: the run stopped at 20 resumes from 10's.
  assert rows[0]["resumed"] and rows[0]["iteration"] == 10 and [r.get("iteration") for r in rows[1:]] == [20, 30]
  for a, b in zip(jax.tree.leaves(nnx.state(reference, nnx.Param)), jax.tree.leaves(nnx.state(resumed, nnx.Param))):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
  with pytest.raises(checkpoint.CheckpointError, match="other settings"):
    joint.train_joint(NANOCRAFT.spec, batch, TrainConfig(iterations=30, hidden=(16,), eval_every=10, seed=2),
                      log=lambda row: None, checkpoint_path=path)


@pytest.mark.slow
def test_an_interrupted_split_search_resumes_to_the_same_result(tmp_path):
  demos = datasets.training_demos(NANOCRAFT, 1, 6, 0)
  validation = datasets.problem_demonstrations(NANOCRAFT, NANOCRAFT.validation_problems(10_001, 3), 0)
  config = TrainConfig(iterations=6, hidden=(8,), eval_every=3, seed=1, split_rounds=2, split_iterations=3,
                             split_hint_iterations=1)
  def parameter_sum(hierarchy) -> float:  # a validation score that tells every hierarchy apart
    return float(sum(np.sum(np.asarray(x, np.float64)) for x in jax.tree.leaves(nnx.state(hierarchy, nnx.Param))))
  reference, report = joint.train_joint(NANOCRAFT.spec, demos, config, parameter_sum, log=lambda row: None,
                                        validation_demos=validation)
  rounds = report["split_search"]
  assert report["capacity"] and 1 <= len(rounds) <= 2 and rounds[0]["candidates"][0][0] == "unchanged"
  assert report["validation"] == parameter_sum(reference)  # the searched hierarchy's, not the snapshot's

  def stop_at_the_first_round(row):
    if "split_search" in row:
      raise KeyboardInterrupt
  path = str(tmp_path / checkpoint.TRAINING_DIR)
  with pytest.raises(KeyboardInterrupt):
    joint.train_joint(NANOCRAFT.spec, demos, config, parameter_sum, log=stop_at_the_first_round,
                      checkpoint_path=path, validation_demos=validation)
  rows = []
  resumed, resumed_report = joint.train_joint(NANOCRAFT.spec, demos, config, parameter_sum, log=rows.append,
                                              checkpoint_path=path, validation_demos=validation)
  # The checkpoint after the iterations: the search starts again, and ends as the uninterrupted one did.
  assert rows[0]["resumed"] and rows[1] == {"split_rounds": 2}
  assert [r["split_search"] for r in rows[2:]] == rounds and resumed_report["split_search"] == rounds
  for a, b in zip(jax.tree.leaves(nnx.state(reference, nnx.Param)), jax.tree.leaves(nnx.state(resumed, nnx.Param))):
    np.testing.assert_allclose(a, b, rtol=1e-5, atol=1e-6)
