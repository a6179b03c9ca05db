"""examples/taxi: the expert solves Taxi by MAXQ's hierarchy, and its stacks are ones the hierarchy file admits."""
import json

import gymnasium
import numpy as np

from examples.taxi import failures, taxi
from php_jax.data import demo_files
from php_jax.envs import gym
from php_jax.training import call_graph


def _fewest_steps(env, start: int) -> int:
  """Fewest actions from state start to a delivery: breadth first over Taxi's transition table."""
  table, frontier, seen = env.unwrapped.P, [start], {start}
  for steps in range(1, 100):
    successors = set()
    for state in frontier:
      for (_, nxt, _, done), in table[state].values():
        if done:
          return steps
        successors.add(nxt)
    frontier = successors - seen
    seen |= frontier
  raise AssertionError("no delivery reachable")


def test_the_maxq_expert_delivers_every_passenger_along_shortest_paths_within_its_declared_calls(tmp_path):
  env, spec = taxi.make_env(), demo_files.read_hierarchy("examples/taxi/taxi.json").spec
  lines = gym.record(env, taxi.MaxqExpert(env), episodes=60, seed=7, annotate=60, spec=spec)
  for i, line in enumerate(lines):
    env.reset(seed=7 + i)
    assert len(line["actions"]) == _fewest_steps(env, env.unwrapped.s)
    returns, terminated = 0.0, False
    for (action,) in line["actions"]:
      _, reward, terminated, _, _ = env.step(action)
      returns += reward
    assert terminated and returns == 20 - (len(line["actions"]) - 1)  # no illegal pickup or dropoff
    row, col, passenger, destination = (int(x) for x in env.unwrapped.decode(env.unwrapped.s))
    assert (row, col) == env.unwrapped.locs[destination] and passenger == destination
  path = tmp_path / "taxi.jsonl"
  path.write_text("".join(json.dumps(line) + "\n" for line in lines))
  demos, _ = demo_files.read_demonstrations(str(path), spec)
  call_graph.check(demos, spec, spec.allowed_ops)  # every step within the file's "calls"
  navigate = {tuple(frames[2]) for line in lines for frames in line["stack"] if frames[2][0] < 4}
  assert {h for h, _ in navigate} == {0, 1, 2, 3} and max(t for _, t in navigate) <= 7


def test_the_landmark_factors_say_which_landmark_the_taxi_stands_on():
  env, plain, rng = taxi.make_env_with_landmarks(), taxi.make_env(), np.random.default_rng(0)
  seen = set()
  for seed in range(40):
    observation, _ = env.reset(seed=seed)
    assert list(observation[:4]) == list(plain.reset(seed=seed)[0])  # the four factors, then four bits
    for _ in range(20):
      row, col = observation[:2]
      on = [int((row, col) == landmark) for landmark in ((0, 0), (0, 4), (4, 0), (4, 3))]  # R, G, Y, B
      assert list(observation[4:]) == on
      seen.add(tuple(on))
      observation, *_ = env.step(int(rng.integers(4)))  # a move (or a bump into a wall)
  assert len(seen) == 5  # off every landmark, and on each of the four


def test_the_waiting_factor_says_whether_the_taxi_stands_where_the_passenger_waits():
  env, plain = taxi.make_env_with_waiting(), taxi.make_env()
  expert, landmarks, seen = taxi.MaxqExpert(env), ((0, 0), (0, 4), (4, 0), (4, 3)), []
  for seed in range(40):
    observation, info = env.reset(seed=seed)
    assert list(observation[:4]) == list(plain.reset(seed=seed)[0])  # the four factors, then the bit
    expert.reset(observation, info)
    terminated = False
    while not terminated:
      row, col, passenger = observation[:3]
      assert observation[4] == int(passenger < 4 and (row, col) == landmarks[passenger])
      seen.append(int(observation[4]))
      action, _ = expert.act(observation, info)
      observation, _, terminated, _, info = env.step(action)
  assert 0 < sum(seen) < len(seen)  # the expert reaches every passenger, so the bit is set before each pickup


def test_failures_names_the_start_pairs_where_get_must_leave_a_landmark():
  env, pairs = gymnasium.make("Taxi-v3"), set()
  for seed in range(300):
    pair = failures.start_pair(env, seed)
    row, col, passenger, _ = env.unwrapped.decode(env.unwrapped.s)
    on = [i for i, landmark in enumerate(env.unwrapped.locs) if (row, col) == tuple(landmark)]
    assert pair == ((on[0], passenger) if on and on[0] != passenger else None)
    pairs.add(pair)
  assert None in pairs and len(pairs) > 6  # most episodes start elsewhere; many pairs occur
