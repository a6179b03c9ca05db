"""FrozenLake (4×4, not slippery) with a two-level expert: the smallest whole example of the expert contract,
which docs/own-environment.md walks through step by step."""
import gymnasium

DOWN, RIGHT = 1, 2
ROUTE = {0: DOWN, 4: DOWN, 8: RIGHT, 9: RIGHT, 10: DOWN, 14: RIGHT}  # cell -> move, around the holes


def make_env() -> gymnasium.Env:
  return gymnasium.make("FrozenLake-v1", is_slippery=False)


class RouteExpert:
  """The root calls `down` or `right` (level 1's procedures 0 and 1), each moving until the route turns."""

  def __init__(self, env):
    self.reset(None, {})

  def reset(self, observation, info):
    self.calls, self.steps, self.move = 0, 0, None  # root's counter, the running call's counter, its move

  def act(self, observation, info):  # observation: the raw cell, an int 0..15 (row * 4 + column)
    move = ROUTE.get(int(observation), DOWN)  # off the route (only on a slippery lake): down
    if self.move is not None and move != self.move:  # the call returns; the root resumes and calls again
      self.calls, self.steps = self.calls + 1, 0
    self.move = move
    stack = [[0, self.calls], [0 if move == DOWN else 1, self.steps]]  # root first: [procedure, counter]
    self.steps += 1
    return move, stack
