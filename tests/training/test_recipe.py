"""The recipe: which candidates the demonstrations leave open, and the choice among them by held-out likelihood."""
import dataclasses
import json

import jax
import numpy as np
import pytest
from flax import nnx

from experiments.common import run_report
from php_jax.envs import datasets, tasks
from php_jax.hierarchy import HierarchySpec
from php_jax.training import call_graph, checkpoint, joint, objective, recipe, selection
from php_jax.training.config import MAX_SEED, TrainConfig
from php_jax.training.networks import make_hierarchy
from php_jax.training.run import Experiment, WorkdirError
from tests import processes
from tests.training.test_segmentation import _demos  # actions-only demonstrations of one factor

NANOCRAFT = tasks.get("nanocraft")


def _names(chosen):
  return [c.name for c in chosen.candidates]


SPEC = HierarchySpec(name="toy", levels=(("root",), ("a", "b"), ("c", "d")), action_sizes=(10,), obs_dim=2)


def test_with_annotation_both_modes_are_tried_each_with_its_call_graph():
  demos = datasets.training_demos(NANOCRAFT, 1, 8, 2)
  chosen = recipe.choose(NANOCRAFT.spec, demos, TrainConfig(), frozenset())
  assert [(c.name, c.settings) for c in chosen.candidates] == [
      ("levelwise", {"training": "levelwise", "call_graph": "all"}),
      ("joint", {"training": "joint", "call_graph": "operations"})]
  assert "2 of 8 demonstrations are annotated" in chosen.reasons[0]
  # a mode asked for (or implied by a setting of one mode only) is the only candidate
  assert recipe.choose(NANOCRAFT.spec, demos, TrainConfig(training="joint"), {"training"}).candidates == (
      recipe.Candidate("joint", {"training": "joint", "call_graph": "operations"}),)
  assert _names(recipe.choose(NANOCRAFT.spec, demos, TrainConfig(strong_warmup=5), {"strong_warmup"})) == ["levelwise"]
  assert _names(recipe.choose(NANOCRAFT.spec, demos, TrainConfig(anneal_temperature=2.0),
                              {"anneal_temperature"})) == ["joint"]
  # a call graph asked for is kept by both modes
  both = recipe.choose(NANOCRAFT.spec, demos, TrainConfig(call_graph="calls"), {"call_graph"})
  assert [c.settings for c in both.candidates] == [{"training": "levelwise"}, {"training": "joint"}]


def test_joint_training_is_not_tried_where_the_annotations_call_graph_leaves_a_step_to_no_procedure():
  """Addition, 3 of 160 annotated (seed 1): the three never show `write` writing a 0, which demonstration 13
  writes first; joint training with that call graph could not explain it, so only level-wise training is
  tried, and joint training asked for gets the narrowest graph that fits (the calls shown, every action)."""
  addition = tasks.get("addition")
  demos = datasets.training_demos(addition, 1, 160, 3)
  with pytest.raises(ValueError, match="demonstration 13, step 0"):
    call_graph.resolve("operations", demos, addition.spec)
  chosen = recipe.choose(addition.spec, demos, TrainConfig(), frozenset(), numbers=range(100, 260))
  assert [(c.name, c.settings) for c in chosen.candidates] == [
      ("levelwise", {"training": "levelwise", "call_graph": "all"})]
  assert "joint training is not tried" in chosen.reasons[0] and "demonstration 113's step 0" in chosen.reasons[0]
  joint_asked = recipe.choose(addition.spec, demos, TrainConfig(training="joint"), {"training"})
  assert joint_asked.candidates == (recipe.Candidate("joint", {"training": "joint", "call_graph": "calls"}),)
  assert "with call graph calls" in joint_asked.reasons[0]
  given = recipe.choose(addition.spec, demos, TrainConfig(call_graph="calls"), {"call_graph"})
  assert _names(given) == ["levelwise", "joint"] and "the call graph asked for" in given.reasons[0]


def test_train_refuses_a_call_graph_that_leaves_a_step_to_no_procedure(tmp_path):
  processes.assert_refused([(["experiments.train", "--task=addition", "--num_strong=3", "--seed=1",
                              "--call_graph=operations", f"--workdir={tmp_path / 'run'}"],
                             "--call_graph=operations: demonstration 13, step 0: no chain of calls")])
  assert not (tmp_path / "run").exists()


@pytest.mark.parametrize("rows, names", [
    ([[1, 1, 9, 2, 2, 9], [1, 9, 2, 9]], ["loops", "unsegmented"]),   # 1 and 2 loop, 9 ends their calls
    ([[1, 2, 3, 1, 2, 4], [3, 1, 2]], ["successors", "unsegmented"]),  # 1 is always followed by 2
    ([[1, 1, 9, 2, 9], [1, 9, 2, 9]], ["loops", "successors", "unsegmented"]),  # both, 2 always followed by 9
    ([[1, 2, 1, 3, 2, 3, 1]], ["unsegmented"])])                        # no loop, no single successor
def test_without_annotation_each_segmentation_that_applies_and_none_are_tried(rows, names):
  demos = _demos(*rows)
  chosen = recipe.choose(SPEC, demos, TrainConfig(), frozenset())
  assert _names(chosen) == names
  assert all(c.settings["training"] == "joint" for c in chosen.candidates)
  assert chosen.candidates[-1].settings == {"training": "joint", "segment_iterations": 0, "split_rounds": 0}


def test_a_segmentation_asked_for_or_a_declared_call_graph_leaves_one_candidate():
  demos = _demos([1, 1, 9, 2, 2, 9])
  assert _names(recipe.choose(SPEC, demos, TrainConfig(segment_rule="successors"), {"segment_rule"})) == ["joint"]
  assert _names(recipe.choose(SPEC, demos, TrainConfig(segment_iterations=0), {"segment_iterations"})) == ["joint"]
  declared = dataclasses.replace(SPEC, allowed_ops=(((True, False),), ((True, False), (False, True)),
                                                    ((True,) * 10, (True,) * 10)))
  chosen = recipe.choose(declared, demos, TrainConfig(), frozenset())
  assert _names(chosen) == ["joint"] and "declares its call graph" in chosen.reasons[0]


def test_restarts_repeat_every_candidate_from_other_initialisations():
  demos = datasets.training_demos(NANOCRAFT, 1, 8, 2)
  chosen = recipe.choose(NANOCRAFT.spec, demos, TrainConfig(seed=7), frozenset(), restarts=2)
  assert _names(chosen) == ["levelwise", "levelwise-restart1", "joint", "joint-restart1"]
  assert [c.config(TrainConfig(seed=7)).network_seed for c in chosen.candidates] == [7, 1007, 7, 1007]
  with pytest.raises(ValueError, match="restarts must be a positive integer"):
    recipe.choose(NANOCRAFT.spec, demos, TrainConfig(), frozenset(), restarts=0)
  last = TrainConfig(init_seed=MAX_SEED - recipe.RESTART_SEED_STRIDE)
  assert len(recipe.choose(NANOCRAFT.spec, demos, last, {"init_seed"}, restarts=2).candidates) == 4
  with pytest.raises(ValueError, match=f"3 restarts initialise the last from seed {MAX_SEED + 1000}, past"):
    recipe.choose(NANOCRAFT.spec, demos, last, {"init_seed"}, restarts=3)


def test_a_level_wise_setting_given_fixes_level_wise_training_even_at_its_default_value():
  demos = datasets.training_demos(NANOCRAFT, 1, 8, 2)
  assert _names(recipe.choose(NANOCRAFT.spec, demos, TrainConfig(root="lstm"), {"root"})) == ["levelwise"]
  assert _names(recipe.choose(NANOCRAFT.spec, demos, TrainConfig(root="lstm"), set())) == ["levelwise", "joint"]


def test_least_capacities_give_the_annotated_calls_room_in_proportion_to_the_lengths_at_most_the_spare():
  demos = _demos([1] * 6, [1] * 9, [1] * 12, strong=[True, True, False])  # the longest, 12, is not annotated
  counters = np.full((3, 12, 3), -1, np.int32)
  counters[0, :6] = [[0, 2, 0]] * 6  # level 1's longest annotated call: 3 operations; level 2's: 1
  counters[1, :9, 0], counters[1, :9, 1] = 0, np.arange(9) % 3
  demos = demos._replace(counters=counters)
  # 3 × 12 / 9 = 4 at level 1 and 1 × 12 / 9 → 2 at level 2; the root's is joint training's own (0)
  assert recipe.least_capacities(demos, 3) == (0, 4, 2)
  assert recipe.least_capacities(demos, 3, most=3) == (0, 3, 2)  # room capped, ...
  assert recipe.least_capacities(demos._replace(length=np.array([6, 9, 40])), 3) == (0, 8, 5)
  counters[:, :, 2] = -1  # a level no annotation shows gets the spare capacity
  assert recipe.least_capacities(demos._replace(counters=counters), 3) == (0, 4, 8)
  with pytest.raises(ValueError, match="needs an annotated demonstration"):
    recipe.least_capacities(demos._replace(strong=np.zeros(3, bool)), 3)


def test_a_score_ranks_what_is_explained_before_how_likely():
  assert selection.rank({selection.EXPLAINED: 3, selection.SCORE: -2.0}) > selection.rank(
      {selection.EXPLAINED: 2, selection.SCORE: -0.1})
  assert selection.rank({selection.EXPLAINED: 3, selection.SCORE: -0.5}) > selection.rank(
      {selection.EXPLAINED: 3, selection.SCORE: -0.6})
  assert selection.rank({selection.EXPLAINED: 0, selection.SCORE: None}) < selection.rank(
      {selection.EXPLAINED: 1, selection.SCORE: -9.0})
  # the training demonstrations explained count with the held-out ones, before how likely
  fewer = {selection.EXPLAINED: 3, selection.TRAINING_EXPLAINED: 60, selection.SCORE: -0.001}
  more = {selection.EXPLAINED: 3, selection.TRAINING_EXPLAINED: 90, selection.SCORE: -0.1}
  assert selection.rank(fewer) < selection.rank(more)
  assert selection.rank(fewer, training=False) > selection.rank(more, training=False)


def test_the_training_demonstrations_a_call_graph_forbids_are_counted(monkeypatch):
  """A call graph read off a few annotated demonstrations can forbid what other demonstrations do (here the
  lowest level's procedures take only actions 1 and 9): `held_out_score` counts the training demonstrations
  some stack explains, whatever the weights, in chunks as in one."""
  training, held_out = _demos([1, 1, 9], [1, 2, 9], [2, 9], [1, 9, 1, 9]), _demos([1, 9])
  only = (None, None, (tuple(a == 1 for a in range(10)), tuple(a == 9 for a in range(10))))
  for graph, explained in ((only, 2), (None, 4)):
    hierarchy = make_hierarchy(SPEC, TrainConfig(hidden=(8,)), graph)
    score = selection.held_out_score(hierarchy, (4, 4, 4), held_out, training)
    assert score[selection.EXPLAINED] == 1 and score[selection.TRAINING_EXPLAINED] == explained
    log_p = objective.demonstration_log_likelihoods(hierarchy, (4, 4, 4), training)
    assert np.isfinite(log_p).sum() == explained and joint.unexplained(hierarchy, (4, 4, 4), training) == 4 - explained
    with monkeypatch.context() as patched:
      patched.setattr(objective, "CHUNK", 3)  # a chunk and a padded one
      np.testing.assert_allclose(objective.demonstration_log_likelihoods(hierarchy, (4, 4, 4), training), log_p,
                                 rtol=1e-6)


def _experiment(demos):
  return Experiment("nanocraft", NANOCRAFT.spec, demos, validate=lambda model: 0.0,
                    test=lambda model: {"tested": 1.0}, extra={"seed": 1},
                    validation_demos=datasets.training_demos(NANOCRAFT, 9, 4, 0))


@pytest.mark.parametrize("trained_first", [True, False])
def test_the_candidate_most_likely_on_held_out_demonstrations_is_kept_and_becomes_the_run(tmp_path, trained_first):
  """Of two candidates, one trained 40 iterations and one a single iteration, the trained one explains the
  held-out demonstrations better and is kept, whichever comes first; its model is the run's; a rerun trains
  nothing; other settings are refused."""
  demos = datasets.training_demos(NANOCRAFT, 1, 6, 6)
  trained, untrained = (recipe.Candidate("trained", {"training": "joint", "iterations": 40}),
                        recipe.Candidate("untrained", {"training": "joint", "iterations": 1}))
  chosen = recipe.Recipe((trained, untrained) if trained_first else (untrained, trained), ("by hand",))
  config = TrainConfig(hidden=(8,), eval_every=20, seed=1)
  rows = []
  results = selection.train_and_choose(_experiment(demos), config, chosen, str(tmp_path), echo=rows.append)
  assert results["recipe"]["chosen"] == "trained" and results["config"]["iterations"] == 40
  scores = {s["name"]: s for s in results["recipe"]["scores"]}
  assert scores["trained"][selection.SCORE] > scores["untrained"][selection.SCORE]
  assert results["test"] == {"tested": 1.0} and json.loads((tmp_path / "results.json").read_text()) == results
  _, kept = checkpoint.load_policy(str(tmp_path))
  _, candidate = checkpoint.load_policy(str(tmp_path / selection.CANDIDATES_DIR / "trained"))
  for a, b in zip(jax.tree.leaves(nnx.state(kept)), jax.tree.leaves(nnx.state(candidate))):
    np.testing.assert_array_equal(a, b)
  assert any(r.get("candidate") == "untrained" for r in rows) and {"chosen": "trained"}.items() <= rows[-3].items()
  page = open(run_report.write(str(tmp_path), demos)).read()
  assert "<h2>Recipe</h2>" in page and "trained (chosen)" in page and "by hand" in page
  rows.clear()
  again = selection.train_and_choose(_experiment(demos), config, chosen, str(tmp_path), echo=rows.append)
  assert again == results and rows == [{"test": results["test"], "wall_seconds": results["wall_seconds"],
                                        "finished_before": True}]
  with pytest.raises(WorkdirError, match="--hidden: \\[8\\] there, \\[16\\] here"):
    selection.train_and_choose(_experiment(demos), dataclasses.replace(config, hidden=(16,)), chosen, str(tmp_path))
  with pytest.raises(WorkdirError, match="other demonstrations"):
    selection.train_and_choose(_experiment(datasets.training_demos(NANOCRAFT, 2, 6, 6)), config, chosen,
                               str(tmp_path))
  with pytest.raises(ValueError, match="2 candidates need held-out demonstrations"):
    selection.train_and_choose(dataclasses.replace(_experiment(demos), validation_demos=None), config, chosen,
                               str(tmp_path / "elsewhere"))
  # one more candidate (as a higher --restarts adds): the finished ones are reused, the new one trained
  more = recipe.Recipe(chosen.candidates + (recipe.Candidate("more", {"training": "joint", "iterations": 2}),),
                       ("by hand",))
  rows.clear()
  results = selection.train_and_choose(_experiment(demos), config, more, str(tmp_path), echo=rows.append)
  assert {r["candidate"] for r in rows if r.get("finished_before")} == {"trained", "untrained"}
  assert any(r.get("candidate") == "more" and "iteration" in r for r in rows)
  assert results["recipe"]["chosen"] == "trained" and len(results["recipe"]["scores"]) == 3


def test_bubble_sort_states_no_segmentation_and_the_recipe_finds_its_rule_in_the_actions():
  bubblesort = tasks.get("bubblesort")
  overrides = bubblesort.defaults.overrides(False)
  assert "segment_rule" not in overrides
  demos = datasets.training_demos(bubblesort, 1, 128, 0)
  chosen = recipe.choose(bubblesort.spec, demos, TrainConfig(**overrides), set(overrides))
  assert _names(chosen) == ["successors", "unsegmented"]
  assert "the loops segmentation does not apply" in chosen.reasons[0]


def test_a_tasks_mode_applies_where_some_demonstration_is_annotated():
  """Bubble sort states level-wise training (joint costs 1.5–2.6× on its long demonstrations), for annotated
  training sets only: without annotation its mode is joint and the segmentation is contested. Addition and
  NanoCraft state no mode: where the annotation's call graph fits every step, both are tried."""
  bubblesort = tasks.get("bubblesort")
  assert bubblesort.defaults.overrides(True)["training"] == "levelwise"
  assert "training" not in bubblesort.defaults.overrides(False)
  for num_strong, names in ((3, ["levelwise"]), (0, ["successors", "unsegmented"])):
    demos = datasets.training_demos(bubblesort, 1, 128, num_strong)
    overrides = bubblesort.defaults.overrides(num_strong > 0)
    assert _names(recipe.choose(bubblesort.spec, demos, TrainConfig(**overrides), set(overrides))) == names
  for name, seed, num_strong in (("addition", 3, 3), ("nanocraft", 1, 8)):
    task = tasks.get(name)
    overrides = task.defaults.overrides(True)
    assert "training" not in overrides and "call_graph" not in overrides
    demos = datasets.training_demos(task, seed, task.defaults.num_demos, num_strong)
    assert _names(recipe.choose(task.spec, demos, TrainConfig(**overrides), set(overrides))) == ["levelwise", "joint"]
