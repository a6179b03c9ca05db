"""Success only where it is known: the rules, and `act`/`record` on environments whose endings are not all
successes (FrozenLake's holes, CartPole's falls, BabyAI's failed missions)."""
from __future__ import annotations

import json
import sys

import gymnasium
import numpy as np
import pytest
from flax import nnx

from php_jax.envs import gym, success
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint
from tests import processes


def _ending(episode_return=0.0, last_reward=None, terminated=False, truncated=False, info=None):
  return success.Ending(episode_return, last_reward, terminated, truncated, info or {})


def test_each_rule_parses_prints_back_and_judges_what_it_says():
  cases = [  # text, printed, ending, success
      ("info:reached", "info:reached", _ending(info={"reached": True}), True),
      ("info:reached", "info:reached", _ending(info={"reached": 0}), False),
      ("info:reached", "info:reached", _ending(terminated=True), False),
      ("return>1.5", "return>1.5", _ending(2.0), True),
      ("return>1.5", "return>1.5", _ending(1.5), False),
      ("return>=1.5", "return>=1.5", _ending(1.5), True),
      ("return > -2", "return>-2", _ending(-1.0), True),
      ("reward>0", "reward>0", _ending(5.0, 0.0), False),
      ("reward>0", "reward>0", _ending(0.0, 0.3), True),
      ("reward>0", "reward>0", _ending(), False),  # no step, no reward
      ("reward>=1e-3", "reward>=0.001", _ending(0.0, 0.001), True),
      ("terminated", "terminated", _ending(terminated=True), True),
      ("terminated", "terminated", _ending(terminated=True, truncated=True), True),  # at the time limit's last step
      ("terminated", "terminated", _ending(truncated=True), False),
      ("terminated", "terminated", _ending(), False),  # ended by the policy
  ]
  for text, printed, ending, expected in cases:
    rule = success.parse(text)
    assert str(rule) == printed and success.judge(rule, ending) is expected, (text, ending)
  for bad in ["", "info:", "return", "return>", "return>x", "reward<0", "done", "terminated!"]:
    with pytest.raises(ValueError, match="is not a success rule: use info:KEY"):
      success.parse(bad)


def test_without_a_rule_success_is_is_success_where_the_environment_reports_it_and_unknown_otherwise():
  reported = [_ending(info={"is_success": True}), _ending(terminated=True), _ending(truncated=True)]
  rule, judged = success.judge_all(None, reported)
  assert str(rule) == "info:is_success" and judged == [True, False, False]
  silent = [_ending(1.0, 1.0, terminated=True), _ending(0.0, 0.0, terminated=True)]
  assert success.judge_all(None, silent) == (None, [None, None])
  first, second = success.summary(None, silent)
  assert first == ('success unknown: no episode\'s last step reported info["is_success"]; --success=info:KEY, '
                   "return>X, reward>X or terminated defines it")
  assert second == "mean return 0.50; 2 terminated, 0 truncated"
  assert success.summary(success.parse("reward>0"), silent + [_ending()]) == [
      "success 0.333 (reward>0)", "mean return 0.33; 2 terminated, 0 truncated, 1 ended by the policy"]
  assert success.summary(None, reported)[0] == (
      "success 0.333 (info:is_success); 2 of 3 episodes did not report it and count as failures: "
      "--success=info:KEY, return>X, reward>X or terminated defines it")
  assert success.summary(success.parse("info:is_success"), reported)[0] == "success 0.333 (info:is_success)"


def test_each_episode_counts_once_in_how_the_episodes_ended_and_no_episodes_print_no_rate():
  at_the_limit = _ending(1.0, 1.0, terminated=True, truncated=True)  # terminal on the time limit's last step
  assert success.summary(success.parse("terminated"), [at_the_limit, _ending(truncated=True)]) == [
      "success 0.500 (terminated)", "mean return 0.50; 1 terminated, 1 truncated"]
  assert success.summary(success.parse("reward>0"), []) == ["no episodes"]


def _random_policy(env: gymnasium.Env, seed: int = 0) -> PHPHierarchy:
  spec = HierarchySpec("random", (("root",), ("a", "b")), gym.action_sizes(env.action_space),
                       gym.observation_size(env.observation_space))
  return PHPHierarchy(spec, hidden=(8,), sample=True, rngs=nnx.Rngs(seed))


def _frozen_lake() -> gymnasium.Env:
  return gymnasium.make("FrozenLake-v1", is_slippery=False, map_name="4x4")


def _babyai() -> gymnasium.Env:
  import minigrid  # noqa: F401  registers the BabyAI levels
  from minigrid.wrappers import ImgObsWrapper
  return ImgObsWrapper(gymnasium.make("BabyAI-PickupDistDebug-v0", max_steps=12))  # a wrong pickup fails


@pytest.mark.parametrize("make_env, rule, truth", [
    (_frozen_lake, "reward>0", lambda e: e["return"] > 0),  # the goal pays 1; holes end the episode with 0
    (lambda: gymnasium.make("CartPole-v1", max_episode_steps=30), "return>=30",  # kept up to the limit
     lambda e: e["return"] >= 30),
    (_babyai, "reward>0", lambda e: e["return"] > 0),  # BabyAI pays only a mission done, and ends failures
])
def test_act_gives_the_true_rate_with_the_rule_and_unknown_without_it(make_env, rule, truth):
  policy = _random_policy(make_env(), seed=2)
  unknown = gym.act(policy, gym.vector_env(make_env, 3), 60, seed=1)
  assert all(e["success"] is None for e in unknown)
  judged = gym.act(policy, gym.vector_env(make_env, 3), 60, seed=1, success_rule=success.parse(rule))
  assert [e["success"] for e in judged] == [truth(e) for e in judged]
  assert [{k: v for k, v in e.items() if k != "success"} for e in judged] == [
      {k: v for k, v in e.items() if k != "success"} for e in unknown]
  terminated = gym.act(policy, gym.vector_env(make_env, 3), 60, seed=1, success_rule=success.parse("terminated"))
  assert [e["success"] for e in terminated] == [e["terminated"] for e in judged]
  # the episodes hold failures that end the episode: counting every ending a success would be wrong here
  assert any(e["terminated"] and not truth(e) for e in judged), judged


def test_act_and_record_commands_print_the_rate_only_under_a_rule(tmp_path):
  env = _frozen_lake()
  policy = tmp_path / "policy"
  policy.mkdir()
  random = _random_policy(env)
  checkpoint.save_hierarchy(str(policy), "random", random, (8,))
  out, judged = tmp_path / "unknown.jsonl", tmp_path / "judged.jsonl"
  act = [sys.executable, "-m", "experiments.act", f"--policy={policy}", "--env=FrozenLake-v1", "--episodes=30",
         "--sample", "--num_envs=2"]
  plain, ruled = processes.run_all([act + [f"--out={out}"], act + [f"--out={judged}", "--success=reward>0"]],
                                   capture_output=True, text=True, timeout=600)
  assert plain.returncode == 0 and ruled.returncode == 0, (plain.stderr, ruled.stderr)
  episodes = [json.loads(line) for line in judged.read_text().splitlines()]
  rate = np.mean([e["return"] > 0 for e in episodes])
  assert [e["success"] for e in episodes] == [e["return"] > 0 for e in episodes]
  assert ruled.stdout.splitlines()[-2] == f"success {rate:.3f} (reward>0)"
  assert [json.loads(line)["success"] for line in out.read_text().splitlines()] == [None] * 30
  assert plain.stdout.splitlines()[-2].startswith(
      'success unknown: no episode\'s last step reported info["is_success"]')
  terminated = sum(e["terminated"] for e in episodes)
  truncated = sum(e["truncated"] for e in episodes)
  assert plain.stdout.splitlines()[-1].endswith(f"{terminated} terminated, {truncated} truncated"
                                                + (f", {30 - terminated - truncated} ended by the policy"
                                                   if terminated + truncated < 30 else ""))


def test_success_flag_refuses_what_is_not_a_rule(tmp_path):
  processes.assert_refused([
      (("experiments.act", f"--policy={tmp_path}", "--env=FrozenLake-v1", "--success=won", f"--out={tmp_path}/o"),
       "--success='won' is not a success rule"),
      (("experiments.record", "--env=FrozenLake-v1", "--expert=a:b", "--episodes=1", "--success=return<1",
        f"--out={tmp_path}/o"), "--success='return<1' is not a success rule"),
  ])


def test_each_copys_info_is_read_out_of_the_vector_environments_batched_infos():
  from php_jax.envs.gym.acting import copy_info
  infos = {"is_success": np.array([True, False]), "_is_success": np.array([True, False]),
           "mission": np.array(["go", {"to": 1}], dtype=object), "_mission": np.array([True, True]),
           "cell": np.array([[1, 2], [3, 4]]), "episode": {"r": np.array([1.0, 2.0])}}
  first, second = copy_info(infos, 0), copy_info(infos, 1)
  assert first["is_success"] is True and "is_success" not in second  # the copy that did not report it
  assert first["mission"] == "go" and second["mission"] == {"to": 1}
  np.testing.assert_array_equal(second["cell"], [3, 4])
  assert "episode" not in first  # a nested dict is not one entry per copy


def test_an_info_key_is_read_without_spaces_and_an_array_value_is_true_where_every_entry_is():
  rule = success.parse("info: done ")
  assert rule.key == "done" and str(rule) == "info:done"
  assert success.judge(rule, _ending(info={"done": np.array([True, True])})) is True
  assert success.judge(rule, _ending(info={"done": np.array([True, False])})) is False
  for nothing in (np.array([]), float("nan"), np.array([1.0, np.nan]), []):
    assert success.judge(rule, _ending(info={"done": nothing})) is False, nothing


def test_the_step_limit_of_an_environment_without_a_spec_is_its_time_limit_wrapper():
  from php_jax.envs.gym.loading import DEFAULT_MAX_STEPS, max_steps_of
  from tests.envs.test_gym import Corridor
  assert max_steps_of(Corridor(), None) == DEFAULT_MAX_STEPS
  assert max_steps_of(gymnasium.wrappers.TimeLimit(Corridor(), 12_345), None) == 12_345
  assert max_steps_of(gymnasium.wrappers.TimeLimit(Corridor(), 12_345), 7) == 7
  copies = gym.vector_env(lambda: gymnasium.wrappers.TimeLimit(Corridor(), 12_345), 2)  # act's, with --num_envs
  assert max_steps_of(copies, None) == 12_345
  assert max_steps_of(gym.vector_env(lambda: gymnasium.make("FrozenLake-v1"), 2), None) == 100


def test_acting_for_no_episodes_is_refused():
  env = _frozen_lake()
  with pytest.raises(ValueError, match="episodes must be a positive integer; got 0"):
    gym.act(_random_policy(env), env, 0, seed=0)
