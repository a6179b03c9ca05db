"""MiniGrid's DoorKey (`MiniGrid-DoorKey-6x6-v0`, package `minigrid`) as a user brings it to php_jax: the
environment with its fully observed state decoded into factors, and an expert that follows a three-part
hierarchy and says so.

  Root -> GetKey, OpenDoor, ReachGoal;  GetKey -> NavigateKey, Pickup;  OpenDoor -> NavigateDoor, Toggle;
  ReachGoal -> NavigateGoal;  Navigate* -> Left, Right, Forward

The agent starts left of a wall with a locked door, a key on its side and the goal in the far corner. As in
Taxi (examples/taxi), a PHP procedure takes no arguments, so each navigation is a procedure of its own, and
every level calls the next, so Pickup and Toggle are one-step procedures of the lowest level. A call never does
nothing: where the agent already faces the key, GetKey calls Pickup at once (likewise the door).
"""
from __future__ import annotations

import collections

import gymnasium
import minigrid  # noqa: F401  (registers the MiniGrid environments)
import numpy as np
from gymnasium import spaces
from minigrid.core.world_object import Door, Key

LEFT, RIGHT, FORWARD, PICKUP, DROP, TOGGLE = range(6)
GET_KEY, OPEN_DOOR, REACH_GOAL = range(3)
NAVIGATE_KEY, PICKUP_PROCEDURE, NAVIGATE_DOOR, TOGGLE_PROCEDURE, NAVIGATE_GOAL = range(5)
DIRECTIONS = ((1, 0), (0, 1), (-1, 0), (0, -1))  # MiniGrid's agent_dir 0..3: right, down, left, up


def _objects(env) -> tuple[tuple[int, int] | None, tuple[int, int], bool]:
  """(key position, None once carried; door position; whether the door is open) of a DoorKey grid."""
  grid, key, door = env.unwrapped.grid, None, None
  for x in range(grid.width):
    for y in range(grid.height):
      cell = grid.get(x, y)
      if isinstance(cell, Key):
        key = (x, y)
      elif isinstance(cell, Door):
        door = (x, y), cell.is_open
  return key, door[0], door[1]


class DoorKeyFactors(gymnasium.ObservationWrapper):
  """The fully observed state as factors: the agent's column, row and direction, the key's column and row
  (0, 0 once carried: a wall cell, never the key's), the door's column and row, and whether it is open."""

  def __init__(self, env: gymnasium.Env):
    super().__init__(env)
    width, height = env.unwrapped.width, env.unwrapped.height
    self.observation_space = spaces.MultiDiscrete([width, height, 4, width, height, width, height, 2])

  def observation(self, observation):
    env = self.env.unwrapped
    key, door, is_open = _objects(self.env)
    return np.array([*env.agent_pos, env.agent_dir, *(key or (0, 0)), *door, int(is_open)], np.int64)


def make_env() -> gymnasium.Env:
  """DoorKey 6×6 with factored observations (the `--env` of record and act)."""
  return DoorKeyFactors(gymnasium.make("MiniGrid-DoorKey-6x6-v0"))


def shortest_turns(passable, start: tuple[int, int, int], done) -> list[int]:
  """The actions (LEFT, RIGHT, FORWARD) of a shortest path from pose start (column, row, direction) to a
  pose where done(pose); passable(column, row) says whether the agent may step onto a cell. Ties: the order
  LEFT, RIGHT, FORWARD."""
  previous = {start: None}
  queue = collections.deque([start])
  while queue:
    pose = queue.popleft()
    if done(pose):
      path = []
      while previous[pose] is not None:
        pose, action = previous[pose]
        path.append(action)
      return path[::-1]
    x, y, d = pose
    dx, dy = DIRECTIONS[d]
    for action, nxt in ((LEFT, (x, y, (d - 1) % 4)), (RIGHT, (x, y, (d + 1) % 4)), (FORWARD, (x + dx, y + dy, d))):
      if nxt not in previous and (action != FORWARD or passable(nxt[0], nxt[1])):
        previous[nxt] = (pose, action)
        queue.append(nxt)
  raise ValueError(f"no path from {start}")


class ThreePartExpert:
  """Gets the key, opens the door and reaches the goal along shortest paths, giving the call stack of every
  action: [[root, τ], [GetKey, OpenDoor or ReachGoal, τ], [a lowest procedure, τ]] (doorkey.json)."""

  def __init__(self, env: gymnasium.Env):
    self.env, self.stack = env, None

  def reset(self, observation, info) -> None:
    self.stack = None

  def act(self, observation, info):
    env = self.env.unwrapped
    key, door, is_open = _objects(self.env)
    x, y = (int(v) for v in env.agent_pos)
    pose = (x, y, int(env.agent_dir))
    front = lambda p: (p[0] + DIRECTIONS[p[2]][0], p[1] + DIRECTIONS[p[2]][1])
    passable = lambda cx, cy: (env.grid.get(cx, cy) is None or env.grid.get(cx, cy).can_overlap())
    if key is not None:
      subtask, target, navigate, finish, act = GET_KEY, key, NAVIGATE_KEY, PICKUP_PROCEDURE, PICKUP
    elif not is_open:
      subtask, target, navigate, finish, act = OPEN_DOOR, door, NAVIGATE_DOOR, TOGGLE_PROCEDURE, TOGGLE
    else:
      goal = (env.width - 2, env.height - 2)
      procedure, action = NAVIGATE_GOAL, shortest_turns(passable, pose, lambda p: p[:2] == goal)[0]
      return self._answer(REACH_GOAL, procedure, action)
    if front(pose) == target:
      return self._answer(subtask, finish, act)
    return self._answer(subtask, navigate, shortest_turns(passable, pose, lambda p: front(p) == target)[0])

  def _answer(self, subtask: int, procedure: int, action: int):
    self.stack = self._next_stack(subtask, procedure)
    return action, [list(frame) for frame in self.stack]

  def _next_stack(self, subtask: int, procedure: int) -> tuple:
    """The stack-machine step to (subtask, procedure): resume the deepest frame that goes on."""
    if self.stack is None:
      return (0, 0), (subtask, 0), (procedure, 0)
    root, middle, lowest = self.stack
    if middle[0] != subtask:
      return (0, root[1] + 1), (subtask, 0), (procedure, 0)
    if lowest[0] != procedure or procedure in (PICKUP_PROCEDURE, TOGGLE_PROCEDURE):
      return root, (subtask, middle[1] + 1), (procedure, 0)
    return root, middle, (procedure, lowest[1] + 1)
