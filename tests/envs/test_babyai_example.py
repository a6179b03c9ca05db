"""examples/babyai: BabyAI's own bot succeeds on GoToLocal, PickupLoc and UnlockPickup, its call stacks are valid,
within babyai.json's calls and mean what the hierarchy says, and the observation wrapper reads MiniGrid's own
view and the mission string."""
import json
import re
import subprocess
import sys

import numpy as np
import pytest

pytest.importorskip("minigrid")

import gymnasium  # noqa: E402
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX  # noqa: E402

from examples.babyai import babyai  # noqa: E402
from php_jax.data import demo_files  # noqa: E402
from php_jax.envs import gym  # noqa: E402
from php_jax.training import call_graph  # noqa: E402

HIERARCHY = "examples/babyai/babyai.json"
VIEW = 7 * 7 * 3  # the view's factors, then the direction, then the mission's 7


def _recorded(level: str, episodes: int, seed: int, tmp_path) -> list[dict]:
  """Every episode annotated, written, read back (which checks every stack) and checked against the calls."""
  env, spec = babyai.make_env(level), demo_files.read_hierarchy(HIERARCHY).spec
  endings = []
  lines = gym.record(env, babyai.BabyAIExpert(env), episodes, seed, annotate=episodes, spec=spec,
                     on_episode=endings.append)
  path = str(tmp_path / f"{level}.jsonl")
  gym.write_demonstrations(path, lines)
  demos, _ = demo_files.read_demonstrations(path, spec)
  call_graph.check(demos, spec, spec.allowed_ops)
  assert sum(ending.last_reward > 0 for ending in endings) >= episodes - 1  # BabyAI's success
  return lines


def _calls(stack: list) -> list[tuple[str, list[tuple[str, list[int]]]]]:
  """An episode's level-1 calls: (part, its level-2 calls as (procedure, the steps they take))."""
  calls = []
  for t, ((_, root), (part, middle), (procedure, lowest)) in enumerate(stack):
    if middle == 0 and lowest == 0:
      calls.append((babyai.PARTS[part], []))
    if lowest == 0:
      calls[-1][1].append((babyai.PROCEDURES[procedure], []))
    calls[-1][1][-1][1].append(t)
  return calls


def _shows_the_object(factors) -> bool:
  """Whether one observation's factors show, in the view, an object of GoToLocal's mission (colour and type)."""
  view, colour, kind = np.asarray(factors[:VIEW]).reshape(49, 3), factors[VIEW + 2], factors[VIEW + 3]
  return bool(np.any((view[:, 0] == OBJECT_TO_IDX[babyai.TYPES[kind - 1]]) & (view[:, 1] == colour - 1)))


@pytest.mark.parametrize("level", [babyai.GO_TO_LOCAL, babyai.PICKUP_LOC, babyai.UNLOCK_PICKUP])
def test_the_recorded_observations_are_the_wrappers_reading_of_minigrids_own(level, tmp_path):
  lines = _recorded(level, 8, 10, tmp_path)
  env, space = gymnasium.make(level), babyai.make_env(level).observation_space
  for i, line in enumerate(lines):
    raw, _ = env.reset(seed=10 + i)
    instruction = env.unwrapped.instrs
    descriptions = [getattr(instruction, name) for name in ("desc", "desc_move", "desc_fixed")
                    if hasattr(instruction, name)]
    mission = [babyai.VERBS.index(re.match("go to|pick up|open|put", raw["mission"])[0])]
    for desc in descriptions + [None] * (2 - len(descriptions)):  # the instruction's objects, as the string says
      mission += [0, 0, 0] if desc is None else [
          COLOR_TO_IDX[desc.color] + 1 if desc.color else 0, babyai.TYPES.index(desc.type or "object") + 1,
          [None, "left", "right", "front", "behind"].index(desc.loc)]
    for t, vector in enumerate(line["observations"]):
      factors = gymnasium.spaces.unflatten(space, np.asarray(vector))
      assert factors[:VIEW].tolist() == raw["image"].reshape(-1).tolist()
      assert factors[VIEW] == raw["direction"] and factors[VIEW + 1:].tolist() == mission
      if t < len(line["actions"]):
        raw, *_ = env.step(line["actions"][t][0])


def test_the_bot_explores_until_it_has_seen_the_mission_object_then_goes_to_it(tmp_path):
  lines = _recorded(babyai.GO_TO_LOCAL, 40, 100, tmp_path)
  space = babyai.make_env().observation_space
  parts = set()
  for line in lines:
    views = [gymnasium.spaces.unflatten(space, np.asarray(v)) for v in line["observations"]]
    seen = np.cumsum([_shows_the_object(f) for f in views]) > 0  # in a view so far
    calls = _calls(line["stack"])
    assert calls[-1][0] == "go_to" and calls[-1][1][-1][0] == "navigate_object"  # the mission's call ends it
    for part, procedures in calls:
      parts.add(part)
      steps = [t for _, taken in procedures for t in taken]
      if part == "explore":
        assert {p for p, _ in procedures} == {"navigate_explore"} and not seen[steps].any()
      else:
        assert part in ("go_to", "unblock") and seen[steps].all()
      if part == "go_to":
        assert {p for p, _ in procedures} == {"navigate_object"}
  assert {"go_to", "explore"} <= parts


def test_unlock_fetches_the_key_opens_the_door_and_puts_the_key_down_before_the_box_is_picked_up(tmp_path):
  lines = _recorded(babyai.UNLOCK_PICKUP, 15, 200, tmp_path)
  env = gymnasium.make(babyai.UNLOCK_PICKUP)
  for i, line in enumerate(lines):
    calls = _calls(line["stack"])
    assert re.fullmatch(r"(explore )?unlock (explore )?pick_up ", "".join(part + " " for part, _ in calls))
    [unlock] = [procedures for part, procedures in calls if part == "unlock"]
    assert re.fullmatch(r"(navigate_key )?pickup (navigate_door )?toggle (navigate_cell )?drop ",
                        "".join(p + " " for p, _ in unlock))
    assert [p for p, _ in calls[-1][1]] in (["navigate_object", "pickup"], ["pickup"])
    env.reset(seed=200 + i)
    door = next(door for room in env.unwrapped.room_grid[0] for door in room.doors if door)
    after = {}
    for t, (action,) in enumerate(line["actions"]):
      env.step(action)
      after[t] = (env.unwrapped.carrying, door.is_open)
    (_, pick), (_, toggle), (_, drop) = [call for call in unlock if call[0] in ("pickup", "toggle", "drop")]
    assert after[pick[0]][0].type == "key" and after[pick[0]][0].color == door.color
    assert after[toggle[0]] == (after[pick[0]][0], True) and after[drop[0]] == (None, True)


def test_each_level_two_call_takes_the_actions_its_procedure_names(tmp_path):
  names = ["left", "right", "forward", "pickup", "drop", "toggle", "done"]
  lengths = {}
  for level in (babyai.GO_TO_LOCAL, babyai.UNLOCK_PICKUP):
    for line in _recorded(level, 10, 300, tmp_path):
      for _, procedures in _calls(line["stack"]):
        for procedure, steps in procedures:
          taken = {names[line["actions"][t][0]] for t in steps}
          lengths.setdefault(procedure, set()).add(len(steps))
          assert taken <= ({"left", "right", "forward"} if procedure.startswith("navigate") else {procedure})
  assert all(lengths[p] == {1} for p in ("pickup", "drop", "toggle"))  # one action each
  assert max(lengths["navigate_object"]) > 3


def test_the_mission_is_read_from_its_string():
  assert babyai.mission_factors("go to the red ball") == [0, 1, 3, 0, 0, 0, 0]
  assert babyai.mission_factors("pick up a key behind you") == [1, 0, 4, 4, 0, 0, 0]
  assert babyai.mission_factors("open the yellow door") == [2, 5, 5, 0, 0, 0, 0]
  assert babyai.mission_factors("put the grey object on your right next to a blue box in front of you") == [
      3, 6, 1, 2, 3, 2, 3]
  largest = babyai.mission_factors("put a grey door behind you next to the grey door behind you")
  assert largest == [n - 1 for n in babyai.MISSION_SIZES]
  for mission in ("go to the red ball, then open a door", "pick up the ball after you open the door",
                  "go to the red ball and go to the blue key", "go to the pink ball"):
    with pytest.raises(ValueError, match="cannot read the mission"):
      babyai.mission_factors(mission)


def test_the_readmes_record_command_writes_what_it_says(tmp_path):
  out = tmp_path / "train.jsonl"
  proc = subprocess.run([sys.executable, "-m", "experiments.record", "--env=examples.babyai.babyai:make_env",
                         "--expert=examples.babyai.babyai:BabyAIExpert", "--episodes=6", "--annotated=2",
                         "--seed=1000", "--success=reward>0", f"--out={out}", f"--hierarchy={HIERARCHY}"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr
  assert "the expert: success 1.000 (reward>0)" in proc.stdout
  lines = [json.loads(line) for line in out.read_text().splitlines()]
  assert [("stack" in line) for line in lines] == [True, True] + [False] * 4
  assert {len(o) for line in lines for o in line["observations"]} == {int(np.sum(
      babyai.make_env().observation_space.nvec))}
