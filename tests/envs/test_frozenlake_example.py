"""examples/frozenlake, the expert docs/own-environment.md walks through: it reaches the goal, its stacks are
the hierarchy file's, and its first three steps are the ones the page shows."""
import re
from pathlib import Path

from examples.frozenlake import frozenlake
from php_jax.data import demo_files
from php_jax.envs import gym, success

ROOT = Path(__file__).resolve().parents[2]


def test_the_route_expert_reaches_the_goal_with_the_stacks_the_page_shows():
  spec = demo_files.read_hierarchy(str(ROOT / "examples" / "frozenlake" / "frozenlake.json")).spec
  endings = []
  lines = gym.record(frozenlake.make_env(), frozenlake.RouteExpert(None), episodes=2, seed=0, annotate=2,
                     spec=spec, on_episode=endings.append)
  assert success.summary(success.parse("reward>0"), endings)[0] == "success 1.000 (reward>0)"
  stacks = lines[0]["stack"]
  assert stacks == [[[0, 0], [0, 0]], [[0, 0], [0, 1]], [[0, 1], [1, 0]], [[0, 1], [1, 1]], [[0, 2], [0, 0]],
                    [[0, 3], [1, 0]]]
  page = (ROOT / "docs" / "own-environment.md").read_text()
  shown = re.findall(r"^  \| (\d) \| (\d+) \| (\w+) \| `(\[\[.*\]\])` \|", page, re.M)
  names = {frozenlake.DOWN: "down", frozenlake.RIGHT: "right"}
  cells = [int(o.index(1.0)) for o in lines[0]["observations"]]
  assert [(int(t), int(cell), action, stack) for t, cell, action, stack in shown] == [
      (t, cells[t], names[lines[0]["actions"][t][0]], str(stacks[t])) for t in range(3)]
  code = (ROOT / "examples" / "frozenlake" / "frozenlake.py").read_text()
  for line in re.search(r"```python\n(.*?)```", page, re.S)[1].splitlines():  # the page's code is the file's
    assert line in code.splitlines(), line
