"""examples/doorkey: the expert solves MiniGrid's DoorKey by its three-part hierarchy, and its stacks are ones
the hierarchy file admits."""
import json
import subprocess
import sys

import pytest

pytest.importorskip("minigrid")

from examples.doorkey import doorkey, failures  # noqa: E402
from php_jax.data import demo_files  # noqa: E402
from php_jax.envs import gym  # noqa: E402
from php_jax.training import call_graph  # noqa: E402


def test_the_expert_reaches_the_goal_in_every_layout_within_its_declared_calls(tmp_path):
  env, spec = doorkey.make_env(), demo_files.read_hierarchy("examples/doorkey/doorkey.json").spec
  lines = gym.record(env, doorkey.ThreePartExpert(env), episodes=40, seed=3, annotate=40, spec=spec)
  layouts = set()
  for i, line in enumerate(lines):
    observation, _ = env.reset(seed=3 + i)
    layouts.add(tuple(observation[3:7]))  # the key's and the door's cells
    for (action,) in line["actions"]:
      _, reward, terminated, truncated, _ = env.step(action)
    assert terminated and not truncated and reward > 0  # at the goal
    assert len(line["actions"]) <= 19
  assert len(layouts) > 20
  path = tmp_path / "doorkey.jsonl"
  path.write_text("".join(json.dumps(line) + "\n" for line in lines))
  demos, _ = demo_files.read_demonstrations(str(path), spec)
  call_graph.check(demos, spec, spec.allowed_ops)  # every step within the file's "calls"
  used = {(frames[1][0], frames[2][0]) for line in lines for frames in line["stack"]}  # (middle, lowest)
  assert {h for _, h in used} == set(range(5)) and {m for m, _ in used} == {0, 1, 2}


def test_the_shortest_turns_face_the_target_and_go_round_walls():
  open_cells = {(1, 1), (2, 1), (3, 1), (1, 2), (3, 2), (1, 3), (2, 3), (3, 3)}  # a ring round a wall at (2, 2)
  passable = lambda x, y: (x, y) in open_cells
  # From (1, 1) facing right, to face (2, 2) from (2, 1): forward, then turn right (down).
  assert doorkey.shortest_turns(passable, (1, 1, 0), lambda p: p == (2, 1, 1)) == [doorkey.FORWARD, doorkey.RIGHT]
  # From (2, 1) facing down (into the wall), to (2, 3): round the wall, 7 actions either way.
  path = doorkey.shortest_turns(passable, (2, 1, 1), lambda p: p[:2] == (2, 3))
  assert len(path) == 7 and path[0] == doorkey.LEFT  # ties: LEFT first, so round by the right-hand side
  with pytest.raises(ValueError, match="no path"):
    doorkey.shortest_turns(passable, (1, 1, 0), lambda p: p[:2] == (2, 2))


def test_failures_counts_the_episodes_that_never_picked_up_the_key_and_where_each_ended():
  level1 = ["get_key", "open_door", "reach_goal"]
  walk, pickup, toggle = [[0, 0], [0, 0], [0, 2]], [[0, 0], [0, 1], [1, 0]], [[0, 1], [1, 0], [3, 5]]
  episodes = [{"success": True, "stack": [walk, pickup, toggle]},
              {"success": False, "stack": [walk, walk]},            # never picks the key up, ends in get_key
              {"success": False, "stack": [walk, pickup, toggle]}]  # ends in open_door, toggling
  assert failures.summarise(episodes, level1, pickup=1) == (
      "failed 2/3; key never picked up 1; ends in get_key 1, open_door 1, reach_goal 0")


def test_calls_of_splits_a_procedures_steps_into_its_calls():
  step = lambda call, h, tau: [[0, 0], [0, call], [h, tau]]  # a new call below when level 1's counter moves on
  stacks = [[step(0, 0, 0), step(0, 0, 1), step(0, 0, 2), step(1, 0, 0), step(2, 1, 0)],
            [step(0, 1, 0), step(1, 0, 0)]]
  assert failures.calls_of(stacks, 0) == [3, 1, 1]
  assert failures.calls_of(stacks, 1) == [1, 1]


def test_failures_refuses_a_workdir_without_a_measured_hierarchy_in_one_line(tmp_path):
  flat = tmp_path / "flat_lstm_d100_a3_s1"  # a flat baseline's finished run: no stacks to read
  flat.mkdir()
  (flat / "episodes.jsonl").write_text(json.dumps({"success": False, "stack": None}) + "\n")
  (flat / "row.json").write_text("{}")
  stopped = tmp_path / "php_d100_a3_s1"  # a PHP run stopped after acting, before decoding: no row.json
  stopped.mkdir()
  (stopped / "episodes.jsonl").write_text(json.dumps({"success": False, "stack": [[[0, 0], [0, 0], [0, 2]]]}) + "\n")
  for workdir in (tmp_path, tmp_path / "missing"):
    proc = subprocess.run([sys.executable, "examples/doorkey/failures.py", f"--workdir={workdir}"],
                          capture_output=True, text=True)
    assert proc.returncode == 2 and not proc.stdout
    assert proc.stderr.strip() == (
        f"--workdir={workdir} holds no PHP run of examples/taxi/measure.py with an episodes.jsonl")
