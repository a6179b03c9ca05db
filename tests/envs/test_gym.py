"""The Gymnasium bridge: spaces as vectors and factors, recording an expert, acting by the executor's rules,
and the record → fit → act commands on an environment defined here."""
from __future__ import annotations

import json
import re
import subprocess
import sys
from typing import NamedTuple

import gymnasium
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from flax import nnx
from gymnasium import spaces

from php_jax import executor
from php_jax.data import demo_files
from php_jax.envs import gym
from php_jax.flat import FlatPolicy
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint
from tests import processes

LENGTH = 6  # corridor cells
LEFT, RIGHT = 0, 1
SPEC = HierarchySpec("corridor", (("root",), ("walk_left", "walk_right")), (2,), 2 + LENGTH)


class Corridor(gymnasium.Env):
  """Walk to the end of a corridor that the observation names: {"goal": 0 (left) or 1, "position": cell}.
  A move off the far end stays put; reaching the goal's end terminates with info["is_success"]."""

  observation_space = spaces.Dict({"goal": spaces.Discrete(2), "position": spaces.Discrete(LENGTH)})
  action_space = spaces.Discrete(2)

  def reset(self, *, seed=None, options=None):
    super().reset(seed=seed)
    self.goal, self.position = int(self.np_random.integers(2)), int(self.np_random.integers(1, LENGTH - 1))
    return self._observation(), {}

  def step(self, action):
    self.position = int(np.clip(self.position + (1 if action == RIGHT else -1), 0, LENGTH - 1))
    done = self.position == (LENGTH - 1 if self.goal else 0)
    return self._observation(), -1.0, done, False, {"is_success": True} if done else {}

  def _observation(self):
    return {"goal": self.goal, "position": self.position}


def make_corridor() -> gymnasium.Env:
  return gymnasium.wrappers.TimeLimit(Corridor(), 20)


class CorridorExpert:
  """Root calls walk_left or walk_right, which steps until the end: stack [[0, 0], [goal, steps so far]]."""

  def __init__(self, env):
    self.steps = 0

  def reset(self, observation, info):
    self.steps = 0

  def act(self, observation, info):
    goal = int(observation["goal"])
    stack = [[0, 0], [goal, self.steps]]
    self.steps += 1
    return (RIGHT if goal else LEFT), stack


class BrokenExpert(CorridorExpert):
  """Its counter skips a value at the second step."""

  def act(self, observation, info):
    action, stack = super().act(observation, info)
    if self.steps == 2:
      stack[1][1] += 1
    return action, stack


class CorridorState(NamedTuple):
  goal: jax.Array
  position: jax.Array
  failed: jax.Array


class PureCorridor:
  """The corridor as a php_jax environment, observing what gym.flatten_observation makes of Corridor's."""

  @staticmethod
  def observe(state):
    return jnp.concatenate([jax.nn.one_hot(state.goal, 2), jax.nn.one_hot(state.position, LENGTH)])

  @staticmethod
  def step(state, action):
    position = jnp.clip(state.position + jnp.where(action[0] == RIGHT, 1, -1), 0, LENGTH - 1)
    return state._replace(position=position)


def test_every_space_kind_flattens_and_others_are_refused():
  space = spaces.Dict({"a": spaces.Discrete(3, start=1), "b": spaces.Tuple(
      (spaces.Box(-1, 1, (2, 2)), spaces.MultiBinary(3), spaces.MultiDiscrete([2, 3])))})
  observation = {"a": 2, "b": (np.full((2, 2), 0.5, np.float32), np.array([1, 0, 1], np.int8), np.array([1, 2]))}
  assert gym.observation_size(space) == 3 + 4 + 3 + 5
  flat = gym.flatten_observation(space, observation)
  assert flat.dtype == np.float32
  np.testing.assert_array_equal(flat, [0, 1, 0, .5, .5, .5, .5, 1, 0, 1, 0, 1, 0, 0, 1])
  for bad, where in [(spaces.Dict({"x": spaces.Sequence(spaces.Discrete(2))}), "observation space['x'] Sequence"),
                     (spaces.Tuple((spaces.Discrete(2), spaces.Graph(spaces.Discrete(2), None))),
                      "observation space[1] Graph")]:
    with pytest.raises(gym.GymError, match=r"^the " + where.replace("[", r"\[").replace("]", r"\]")):
      gym.observation_size(bad)


class Fixed(gymnasium.Env):
  """Observes a fixed sample of its space."""

  def __init__(self, space, seed):
    self.observation_space, self.action_space = space, spaces.Discrete(2)
    space.seed(seed)
    self.observation = space.sample()

  def reset(self, *, seed=None, options=None):
    return self.observation, {}


@pytest.mark.parametrize("space", [
    spaces.Discrete(4, start=1), spaces.Box(-2, 2, (2, 3)), spaces.MultiBinary(5),
    spaces.MultiDiscrete([5, 5, 4]), spaces.MultiDiscrete([[2, 3], [4, 5]], start=[[1, 0], [0, 2]]),
    spaces.Dict({"a": spaces.Discrete(3), "b": spaces.Box(0, 1, (2,))})])
def test_a_vector_environments_observations_flatten_copy_by_copy(space):
  envs = gymnasium.vector.SyncVectorEnv([lambda s=s: Fixed(space, s) for s in range(3)])
  observations, _ = envs.reset()
  rows = gym.flatten_batch(envs, observations)
  assert rows.shape == (3, gym.observation_size(space)) and rows.dtype == np.float32
  for row, one in zip(rows, [env.observation for env in envs.envs]):
    np.testing.assert_array_equal(row, gym.flatten_observation(space, one))


def test_action_factors_round_trip_and_other_action_spaces_are_refused():
  discrete, multi = spaces.Discrete(4, start=2), spaces.MultiDiscrete([[2, 3], [4, 5]], start=[[1, 0], [0, 2]])
  assert gym.action_sizes(discrete) == (4,) and gym.action_sizes(multi) == (2, 3, 4, 5)
  for space in (discrete, multi):
    space.seed(0)
    actions = [space.sample() for _ in range(20)]
    factors = [gym.action_factors(space, a) for a in actions]
    assert all(0 <= f < n for row in factors for f, n in zip(row, gym.action_sizes(space)))
    back = gym.env_actions(space, factors)
    np.testing.assert_array_equal(back, np.stack(actions))
    assert all(space.contains(a) for a in back)
  with pytest.raises(gym.GymError, match="action space Box"):
    gym.action_sizes(spaces.Box(0, 1, (2,)))


def test_record_keeps_the_first_episodes_stacks_and_writes_readable_lines(tmp_path):
  lines = gym.record(make_corridor(), CorridorExpert(None), episodes=5, seed=3, annotate=2, spec=SPEC)
  assert ["stack" in line for line in lines] == [True, True, False, False, False]
  ended = []
  again = gym.record(make_corridor(), CorridorExpert(None), episodes=5, seed=3, annotate=2,
                     on_episode=ended.append)
  assert again == lines and len(ended) == 5  # episode i is reset with seed + i; each end told once
  assert [e.episode_return for e in ended] == [-len(line["actions"]) for line in lines]
  assert all(e.terminated and not e.truncated and e.info == {"is_success": True} for e in ended)
  first = lines[0]
  assert len(first["observations"]) == len(first["actions"]) + 1
  goal = int(np.argmax(first["observations"][0][:2]))
  assert first["stack"] == [[[0, 0], [goal, t]] for t in range(len(first["actions"]))]
  path = tmp_path / "demos.jsonl"
  path.write_text("".join(json.dumps(line) + "\n" for line in lines))
  batch, spec = demo_files.read_demonstrations(str(path), SPEC)
  assert spec.obs_dim == 8 and list(batch.strong) == [True, True, False, False, False]
  chosen = gym.record(make_corridor(), CorridorExpert(None), episodes=5, seed=3, annotate=[4, 1])
  assert ["stack" in line for line in chosen] == [False, True, False, False, True]
  assert chosen[1] == lines[1] and chosen[0] == {k: lines[0][k] for k in ("observations", "actions")}


def test_record_refuses_a_broken_stack_a_bad_action_and_missing_stacks_naming_episode_and_step():
  with pytest.raises(gym.GymError, match=r"^episode 0: stack step 1: "):
    gym.record(make_corridor(), BrokenExpert(None), episodes=2, seed=1, annotate=1)

  class OutOfSpace(CorridorExpert):
    def act(self, observation, info):
      return 2, None

  with pytest.raises(gym.GymError, match=r"^episode 0, step 0: the expert's action 2 is not in"):
    gym.record(make_corridor(), OutOfSpace(None), episodes=1, seed=0)

  class Silent(CorridorExpert):
    def act(self, observation, info):
      return super().act(observation, info)[0]

  with pytest.raises(gym.GymError, match=r"^episode 0 is to be annotated, but the expert gave no call stack"):
    gym.record(make_corridor(), Silent(None), episodes=1, seed=0, annotate=1)
  assert all("stack" not in line for line in gym.record(make_corridor(), Silent(None), episodes=2, seed=0))
  class Huge(CorridorExpert):
    def act(self, observation, info):
      action, stack = super().act(observation, info)
      return action, [stack[0], [10**12, stack[1][1]]]

  with pytest.raises(gym.GymError, match=r"^episode 0, step 0: the expert's procedure id 1000000000000 at level 1 "
                                         "is beyond 4095"):
    gym.record(make_corridor(), Huge(None), episodes=1, seed=0, annotate=1)
  with pytest.raises(gym.GymError, match=r"^episode 0: stack step 0: procedure id 1 at level 1 is unknown"):
    narrow = HierarchySpec("c", (("root",), ("walk",)), (2,), 8)  # episode 0 (seed 0) walks right
    gym.record(make_corridor(), CorridorExpert(None), episodes=1, seed=0, annotate=1, spec=narrow)


class _Failing(gymnasium.Env):
  """Five steps of nothing on a Box observation, its step() raising at step fail_at or its observation NaN from
  step nan_from."""
  observation_space = spaces.Box(-np.inf, np.inf, (2,), np.float32)
  action_space = spaces.Discrete(2)

  def __init__(self, fail_at=None, nan_from=None):
    self.fail_at, self.nan_from, self.t = fail_at, nan_from, 0

  def _observation(self):
    return np.array([np.nan if self.nan_from is not None and self.t >= self.nan_from else 0.0, 1.0], np.float32)

  def reset(self, *, seed=None, options=None):
    super().reset(seed=seed)
    self.t = 0
    return self._observation(), {}

  def step(self, action):
    self.t += 1
    if self.t == self.fail_at:
      raise RuntimeError("the motor stalled")
    return self._observation(), 0.0, self.t >= 5, False, {}


class _Idle:
  def __init__(self, env=None):
    pass

  def act(self, observation, info):
    return 0


def test_an_environment_or_expert_that_fails_or_observes_nan_is_named_with_episode_and_step():
  with pytest.raises(gym.GymError, match=r"^episode 0, step 1: the environment's step\(\) failed: RuntimeError: "
                                         "the motor stalled$"):
    gym.record(_Failing(fail_at=2), _Idle(), episodes=1, seed=0)
  with pytest.raises(gym.GymError, match=r"^episode 0, step 2: the environment's observation holds NaN"):
    gym.record(_Failing(nan_from=2), _Idle(), episodes=1, seed=0)

  class ResetFails(CorridorExpert):
    def reset(self, observation, info):
      raise KeyError("goal")

  with pytest.raises(gym.GymError, match=r"^episode 0, step 0: the expert's reset\(\) failed: KeyError: 'goal'"):
    gym.record(make_corridor(), ResetFails(None), episodes=1, seed=0)
  policy = PHPHierarchy(HierarchySpec("idle", (("root",), ("a",)), (2,), 2), hidden=(4,), rngs=nnx.Rngs(0))
  for level in policy.levels:  # never stop: the environment ends each episode
    level.termination.biases[-1][...] = jnp.full_like(level.termination.biases[-1][...], -30.0)
  with pytest.raises(gym.GymError, match=r"^acting: the environment's step\(\) failed: RuntimeError: the motor"):
    gym.act(policy, _Failing(fail_at=3), 2, seed=0)
  with pytest.raises(gym.GymError, match=r"^episode 0, step 2: the environment's observation holds NaN"):
    gym.act(policy, _Failing(nan_from=2), 2, seed=0)
  gymnasium.register("PhpJaxUnmakeable-v0", entry_point=_unmakeable)  # as LunarLander without Box2D
  with pytest.raises(gym.GymError, match=r"^environment 'PhpJaxUnmakeable-v0': making it failed: "
                                         "DependencyNotInstalled: Box2D is not installed"):
    gym.env_maker("PhpJaxUnmakeable-v0")()


def _unmakeable():
  raise gymnasium.error.DependencyNotInstalled("Box2D is not installed")


class TupleExpert(CorridorExpert):
  """CorridorExpert's choices, its stack as a tuple of tuples of NumPy ints."""

  def act(self, observation, info):
    action, stack = super().act(observation, info)
    return np.int64(action), tuple((np.int64(p), np.int32(c)) for p, c in stack)


class DeepeningExpert(CorridorExpert):
  """Its stack gains a level at the second step."""

  def act(self, observation, info):
    action, stack = super().act(observation, info)
    return action, stack + [[0, 0]] if self.steps == 2 else stack


class FixedWalker:
  """Walks right, then down, then right...: an expert for FrozenLake that knows nothing of its holes."""

  def __init__(self, env):
    self.t = 0

  def act(self, observation, info):
    self.t += 1
    return 2 if self.t % 2 else 1


def test_a_step_limit_is_the_environments_own_time_limit():
  ended = []
  lines = gym.record(gymnasium.wrappers.TimeLimit(make_corridor(), 2), CorridorExpert(None), episodes=6, seed=0,
                     on_episode=ended.append)
  assert all(len(line["actions"]) <= 2 for line in lines) and any(len(line["actions"]) == 2 for line in lines)
  assert [e.truncated for e in ended] == [len(line["actions"]) == 2 for line in lines]
  assert any(e.terminated and e.truncated for e in ended)  # the goal reached on the limit's step: both, as Gymnasium says


def test_record_takes_any_sequence_for_a_stack_and_names_a_malformed_one():
  lists = gym.record(make_corridor(), CorridorExpert(None), episodes=3, seed=2, annotate=3, spec=SPEC)
  assert gym.record(make_corridor(), TupleExpert(None), episodes=3, seed=2, annotate=3, spec=SPEC) == lists
  with pytest.raises(gym.GymError, match=r"^episode 0, step 1: the expert's stack has 3 levels; at step 0 it had 2"):
    gym.record(make_corridor(), DeepeningExpert(None), episodes=1, seed=0, annotate=1)

  class Shallow(CorridorExpert):
    def act(self, observation, info):
      return super().act(observation, info)[0], [[0, 0]]

  with pytest.raises(gym.GymError, match=r"^episode 0, step 0: the expert's stack \[\[0, 0\]\] has fewer than two"):
    gym.record(make_corridor(), Shallow(None), episodes=1, seed=0, annotate=1)


def test_record_makes_its_folder_takes_module_env_id_and_judges_the_expert(tmp_path):
  corridor, lake = tmp_path / "new" / "folder" / "demos.jsonl", tmp_path / "lake" / "demos.jsonl"
  made, walked, judged = processes.run_all([
      [sys.executable, "-m", "experiments.record", "--env=tests.envs.test_gym:make_corridor",
       "--expert=tests.envs.test_gym:CorridorExpert", "--episodes=4", "--annotated=1", f"--out={corridor}"],
      [sys.executable, "-m", "experiments.record", "--env=gymnasium:FrozenLake-v1",
       "--expert=tests.envs.test_gym:FixedWalker", "--episodes=5", f"--out={lake}"],
      [sys.executable, "-m", "experiments.record", "--env=gymnasium:FrozenLake-v1",
       "--expert=tests.envs.test_gym:FixedWalker", "--episodes=5", "--success=reward>0", f"--out={lake}"],
  ], capture_output=True, text=True, timeout=600)
  assert made.returncode == 0 and len(corridor.read_text().splitlines()) == 4, made.stderr
  assert made.stdout.splitlines()[-2] == "the expert: success 1.000 (info:is_success)"
  assert walked.returncode == 0 and len(lake.read_text().splitlines()) == 5, walked.stderr
  assert walked.stdout.splitlines()[-2].startswith("the expert: success unknown: no episode's last step reported")
  assert judged.returncode == 0 and re.fullmatch(r"the expert: success 0\.\d{3} \(reward>0\)",
                                                 judged.stdout.splitlines()[-2]), judged.stdout


def _random_hierarchy(seed: int) -> PHPHierarchy:
  return PHPHierarchy(SPEC, hidden=(8,), rngs=nnx.Rngs(seed))


@pytest.mark.parametrize("num_envs", [1, 3])
def test_act_follows_the_executor_step_for_step(num_envs):
  """A randomly initialised hierarchy in the Gymnasium corridor takes the actions, and holds the stacks,
  that the executor gives it in the same corridor written as a php_jax environment."""
  policy, episodes = _random_hierarchy(0), 7
  envs = gym.vector_env(make_corridor, num_envs)
  outcomes = gym.act(policy, envs, episodes, seed=5)
  starts = [Corridor().reset(seed=5 + i)[0] for i in range(episodes)]
  states = CorridorState(jnp.array([s["goal"] for s in starts]), jnp.array([s["position"] for s in starts]),
                         jnp.zeros(episodes, bool))
  rollout = executor.rollout_batch(policy, SPEC, PureCorridor(), states, jax.random.split(jax.random.key(0),
                                                                                          episodes), 20)
  some_reached = any(o["terminated"] for o in outcomes)  # the corridor reports is_success only when reached
  for i, outcome in enumerate(outcomes):
    steps = int(rollout.length[i])
    assert outcome["steps"] == steps and outcome["return"] == -steps
    expected = np.stack([rollout.procedures[i, :steps], rollout.counters[i, :steps]], -1).tolist()
    assert outcome["stack"] == expected
    final = int(rollout.final_state.position[i])
    reached = final == (LENGTH - 1 if starts[i]["goal"] else 0)
    assert outcome["terminated"] == reached and outcome["success"] == (reached if some_reached else None)
    assert outcome["truncated"] == (steps == 20 and not reached)


def test_a_sampling_hierarchy_acts_the_same_for_the_same_seed_whatever_the_number_of_copies():
  policy = PHPHierarchy(SPEC, hidden=(8,), sample=True, rngs=nnx.Rngs(3))
  one = gym.act(policy, make_corridor(), 6, seed=11)
  ended = []
  assert gym.act(policy, gym.vector_env(make_corridor, 4), 6, seed=11, on_episode=ended.append) == one
  assert len(ended) == 6  # each episode's end told once, whichever copy ran it
  policy.sample = False
  assert gym.act(policy, make_corridor(), 6, seed=11) != one  # the greedy choices on the same episodes


def test_act_refuses_a_policy_sized_for_another_environment():
  other = PHPHierarchy(HierarchySpec("c", SPEC.levels, (2,), 9), hidden=(8,), rngs=nnx.Rngs(0))
  with pytest.raises(gym.GymError, match="observes vectors of 9 numbers; this environment's observations "
                                         "flatten to 8"):
    gym.act(other, make_corridor(), 1, 0)
  lstm = FlatPolicy(8, (3,), 4, rngs=nnx.Rngs(0))
  with pytest.raises(gym.GymError, match=r"factor sizes \[3\]; this environment's Discrete\(2\) has \[2\]"):
    gym.act(lstm, make_corridor(), 1, 0)


def test_a_flat_lstm_acts_through_the_same_loop():
  outcomes = gym.act(FlatPolicy(8, (2,), 4, rngs=nnx.Rngs(1)), gym.vector_env(make_corridor, 2), 4, seed=0)
  assert len(outcomes) == 4 and all(o["stack"] is None and 0 <= o["steps"] <= 20 for o in outcomes)


def test_a_sampling_flat_lstm_acts_the_same_for_the_same_seed_whatever_the_number_of_copies():
  policy = FlatPolicy(8, (2,), 4, sample=True, rngs=nnx.Rngs(1))
  one = gym.act(policy, make_corridor(), 8, seed=11)
  assert gym.act(policy, gym.vector_env(make_corridor, 3), 8, seed=11) == one
  assert gym.act(policy, make_corridor(), 8, seed=12) != one
  policy.sample = False
  assert gym.act(policy, make_corridor(), 8, seed=11) != one  # the greedy choices on the same episodes


def _run(*args):
  return subprocess.run([sys.executable, "-m", *args], capture_output=True, text=True, timeout=600)


CORRIDOR_HIERARCHY = {"levels": [["root"], ["walk_left", "walk_right"]], "action_sizes": [2],
                      "capacity": [None, LENGTH]}


def test_recorded_demonstrations_fit_a_hierarchy_that_solves_the_environment(tmp_path):
  demos, run = tmp_path / "demos.jsonl", tmp_path / "run"
  (tmp_path / "corridor.json").write_text(json.dumps(CORRIDOR_HIERARCHY))
  lines = gym.record(make_corridor(), CorridorExpert(None), episodes=24, seed=0, annotate=4)
  demos.write_text("".join(json.dumps(line) + "\n" for line in lines))
  proc = _run("experiments.fit", f"--demos={demos}", f"--hierarchy={tmp_path / 'corridor.json'}",
              f"--workdir={run}", "--iterations=150", "--eval_every=50", "--hidden=16", "--learning_rate=0.03",
              "--noreport")
  assert proc.returncode == 0, proc.stderr
  assert not (run / "report.html").exists()
  _, policy = checkpoint.load_policy(str(run))
  episodes = gym.act(policy, gym.vector_env(make_corridor, 4), 20, seed=100)
  assert all(e["success"] and e["steps"] == len(e["stack"]) for e in episodes), episodes


@pytest.mark.slow
def test_record_fit_act_commands_on_an_environment_php_jax_has_never_seen(tmp_path):
  hierarchy, demos, run = tmp_path / "corridor.json", tmp_path / "demos.jsonl", tmp_path / "run"
  hierarchy.write_text(json.dumps(CORRIDOR_HIERARCHY))
  env, expert = "--env=tests.envs.test_gym:make_corridor", "--expert=tests.envs.test_gym:CorridorExpert"
  proc = _run("experiments.record", env, expert, "--episodes=24", "--annotated=4", "--seed=0", f"--out={demos}",
              f"--hierarchy={hierarchy}")
  assert proc.returncode == 0 and "24 episodes (4 annotated)" in proc.stdout, proc.stderr
  suggested, chosen = tmp_path / "suggested.jsonl", tmp_path / "chosen.jsonl"
  suggested.write_text('{"index": 7, "score": 3, "why": "-"}\n{"index": 5, "score": 3, "why": "-"}\n')
  proc = _run("experiments.record", env, expert, "--episodes=24", f"--annotate={suggested}", "--seed=0",
              f"--out={chosen}")
  assert proc.returncode == 0 and "24 episodes (2 annotated)" in proc.stdout, proc.stderr
  lines = [json.loads(line) for line in chosen.read_text().splitlines()]
  assert [i for i, line in enumerate(lines) if "stack" in line] == [5, 7]
  recorded = [json.loads(line)["actions"] for line in demos.read_text().splitlines()]
  assert [line["actions"] for line in lines] == recorded  # the same episodes, only the stacks differ
  proc = _run("experiments.fit", f"--demos={demos}", f"--hierarchy={hierarchy}", f"--workdir={run}",
              "--iterations=150", "--eval_every=50", "--hidden=16", "--learning_rate=0.03")
  assert proc.returncode == 0, proc.stderr
  out = tmp_path / "episodes.jsonl"
  proc = _run("experiments.act", f"--policy={run}", env, "--episodes=20", "--seed=100", "--num_envs=4",
              f"--out={out}")
  assert proc.returncode == 0, proc.stderr
  episodes = [json.loads(line) for line in out.read_text().splitlines()]
  assert len(episodes) == 20 and set(episodes[0]) == {"return", "steps", "success", "terminated", "truncated",
                                                      "stack"}
  assert all(e["success"] for e in episodes), episodes
  assert proc.stdout.strip().splitlines()[-2:] == [
      "success 1.000 (info:is_success)",
      f"mean return {np.mean([e['return'] for e in episodes]):.2f}; 20 terminated, 0 truncated"]
  flat = tmp_path / "flat"
  proc = _run("experiments.fit", f"--demos={demos}", f"--hierarchy={hierarchy}", f"--workdir={flat}",
              "--model=flat_gru", "--flat_hidden=8", "--iterations=20", "--eval_every=10")
  assert proc.returncode == 0, proc.stderr
  results = json.loads((flat / "results.json").read_text())
  assert results["model"] == "flat_gru" and results["flat_gru"]["hidden"] == 8
  proc = _run("experiments.act", f"--policy={flat}", env, "--episodes=3", "--sample", f"--out={out}")
  assert proc.returncode == 0, proc.stderr
  assert [json.loads(line)["stack"] for line in out.read_text().splitlines()] == [None] * 3


def test_unknown_environments_and_experts_are_refused_naming_them():
  with pytest.raises(gym.GymError, match="^unknown environment 'NoSuchEnv-v0': "):
    gym.env_maker("NoSuchEnv-v0")
  with pytest.raises(gym.GymError, match="^cannot load environment 'tests.envs.test_gym:no_such': AttributeError"):
    gym.env_maker("tests.envs.test_gym:no_such")
  with pytest.raises(gym.GymError, match="^environment 'tests.envs.test_gym:LENGTH' is a int, not a callable"):
    gym.env_maker("tests.envs.test_gym:LENGTH")
  with pytest.raises(gym.GymError, match="^cannot load expert 'no_such:Expert': ModuleNotFoundError"):
    gym.expert_maker("no_such:Expert")


def test_record_and_act_refusals_end_in_one_line_and_exit_2(tmp_path):
  out, wide, flat = tmp_path / "out.jsonl", tmp_path / "wide", tmp_path / "flat"
  wide.mkdir()
  flat.mkdir()
  checkpoint.save_hierarchy(str(wide), "c", PHPHierarchy(HierarchySpec("c", SPEC.levels, (2,), 9), hidden=(8,),
                                                         rngs=nnx.Rngs(0)), (8,))
  checkpoint.save_flat(str(flat), "c", FlatPolicy(8, (2,), 4, rngs=nnx.Rngs(0)), SPEC)
  env, expert = "--env=tests.envs.test_gym:make_corridor", "--expert=tests.envs.test_gym:CorridorExpert"
  record = ("experiments.record", env, expert, f"--out={out}")
  chosen = tmp_path / "chosen.jsonl"
  chosen.write_text('{"index": 0}\n{"index": 2}\n')
  cases = [
      ((*record, "--episodes=2", f"--annotate={chosen}"),
       f"--annotate: {chosen}:2: each line needs an \"index\" in 0..1"),
      ((*record, "--episodes=3", "--annotated=1", f"--annotate={chosen}"),
       "--annotate and --annotated: give one of them"),
      (("experiments.record", env, "--expert=tests.envs.test_gym:BrokenExpert", "--episodes=2", "--annotated=1",
        "--seed=1", f"--out={out}"), "episode 0: stack step 1: "),
      (("experiments.act", f"--policy={wide}", env, f"--out={out}"),
       f"--policy={wide} does not fit {env}: the policy observes vectors of 9 numbers"),
      ((*record, "--episodes=2", "--annotated=3"), "--annotated=3 is more than --episodes=2"),
      ((*record, "--episodes=0"), "--episodes=0"),
      ((*record, "--episodes=2", "--annotated=-1"), "--annotated=-1"),
      ((*record, "--episodes=1", "--seed=99999999999"), "99999999999 is not an integer in the range [0, 2147483647]"),
      ((*record, "--episodes=2", "--seed=-1"), "--seed=-1"),
      ((*record, "--episodes=2", "--max_steps=0"), "--max_steps=0"),
      (("experiments.act", f"--policy={flat}", env, "--num_envs=0", f"--out={out}"), "--num_envs=0"),
  ]
  processes.assert_refused(cases)
  assert not out.exists()
