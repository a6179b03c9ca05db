"""Taxi (Gymnasium's `Taxi-v3`, Dietterich 2000) as a user brings it to php_jax: the environment with its
state number decoded into factors, and an expert that follows the MAXQ hierarchy and says so.

  Root -> Get, Put;  Get -> Navigate(passenger), Pickup;  Put -> Navigate(destination), Putdown;
  Navigate(t) -> South, North, East, West

A PHP procedure takes no arguments, so Navigate(t) is one procedure per landmark t (R, G, Y, B), and every
level calls the next, so Pickup and Putdown are one-step procedures of the lowest level. A call never does
nothing: where the taxi already stands on the landmark, Get (or Put) calls Pickup (Putdown) at once.
"""
from __future__ import annotations

import collections

import gymnasium
import numpy as np
from gymnasium import spaces

SOUTH, NORTH, EAST, WEST, PICKUP, DROPOFF = range(6)
GET, PUT = range(2)
NAVIGATE = (0, 1, 2, 3)   # to R, G, Y, B: the lowest level's first four procedures
PICKUP_PROCEDURE, PUTDOWN_PROCEDURE = 4, 5
IN_TAXI = 4               # the passenger location while the passenger rides


class TaxiFactors(gymnasium.ObservationWrapper):
  """Taxi's state number (one of 500) as its four factors: taxi row, taxi column, passenger location (R, G,
  Y, B, or 4: in the taxi) and destination (R, G, Y, B), so that networks can generalise across states."""

  def __init__(self, env: gymnasium.Env):
    super().__init__(env)
    self.observation_space = spaces.MultiDiscrete([5, 5, 5, 4])

  def observation(self, observation):
    return np.array(list(self.env.unwrapped.decode(observation)), np.int64)


class TaxiFactorsAndLandmarks(TaxiFactors):
  """TaxiFactors and, for each landmark (R, G, Y, B), whether the taxi stands on it: what a user who knows
  the map might add, so that the networks need not learn which cells are landmarks."""

  def __init__(self, env: gymnasium.Env):
    super().__init__(env)
    self.observation_space = spaces.MultiDiscrete([5, 5, 5, 4, 2, 2, 2, 2])

  def observation(self, observation):
    row, col, passenger, destination = super().observation(observation)
    on = [int((row, col) == tuple(landmark)) for landmark in self.env.unwrapped.locs]
    return np.array([row, col, passenger, destination, *on], np.int64)


class TaxiFactorsAndWaiting(TaxiFactors):
  """TaxiFactors and whether the taxi stands where the passenger waits: the one conjunction (the taxi's cell
  and the passenger's landmark) on which Get's first choice, Pickup or a Navigate, depends."""

  def __init__(self, env: gymnasium.Env):
    super().__init__(env)
    self.observation_space = spaces.MultiDiscrete([5, 5, 5, 4, 2])

  def observation(self, observation):
    row, col, passenger, destination = super().observation(observation)
    waiting = passenger != IN_TAXI and (row, col) == tuple(self.env.unwrapped.locs[passenger])
    return np.array([row, col, passenger, destination, int(waiting)], np.int64)


def make_env() -> gymnasium.Env:
  """Taxi-v3 with factored observations (the `--env` of record and act)."""
  return TaxiFactors(gymnasium.make("Taxi-v3"))


def make_env_with_landmarks() -> gymnasium.Env:
  """Taxi-v3 with factored observations and the landmarks the taxi stands on."""
  return TaxiFactorsAndLandmarks(gymnasium.make("Taxi-v3"))


def make_env_with_waiting() -> gymnasium.Env:
  """Taxi-v3 with factored observations and whether the taxi stands where the passenger waits."""
  return TaxiFactorsAndWaiting(gymnasium.make("Taxi-v3"))


def _moves(desc: np.ndarray, row: int, col: int):
  """(action, (row, col)) for every move that leaves cell (row, col) on the map `desc`."""
  rows, cols = desc.shape[0] - 2, (desc.shape[1] - 1) // 2
  if row + 1 < rows:
    yield SOUTH, (row + 1, col)
  if row > 0:
    yield NORTH, (row - 1, col)
  if col + 1 < cols and desc[row + 1, 2 * col + 2] == b":":
    yield EAST, (row, col + 1)
  if col > 0 and desc[row + 1, 2 * col] == b":":
    yield WEST, (row, col - 1)


def shortest_moves(desc: np.ndarray, target: tuple[int, int]) -> dict[tuple[int, int], int]:
  """Per cell the first move of a shortest path to target (ties: South, North, East, West first)."""
  distance = {target: 0}
  queue = collections.deque([target])
  while queue:  # breadth first from the target; every move can be undone, so distances are symmetric
    cell = queue.popleft()
    for _, neighbour in _moves(desc, *cell):
      if neighbour not in distance:
        distance[neighbour] = distance[cell] + 1
        queue.append(neighbour)
  return {cell: next(a for a, n in _moves(desc, *cell) if distance[n] == distance[cell] - 1)
          for cell in distance if cell != target}


class MaxqExpert:
  """Drives the taxi by the MAXQ hierarchy along shortest paths, giving the call stack of every action:
  [[root, τ], [Get or Put, τ], [Navigate(t), Pickup or Putdown, τ]] (the hierarchy of taxi.json)."""

  def __init__(self, env: gymnasium.Env):
    self.landmarks = tuple(env.unwrapped.locs)
    self.routes = [shortest_moves(env.unwrapped.desc, t) for t in self.landmarks]
    self.stack = None

  def reset(self, observation, info) -> None:
    self.stack = None

  def act(self, observation, info):
    row, col, passenger, destination = (int(x) for x in observation[:4])
    subtask = PUT if passenger == IN_TAXI else GET
    target = destination if subtask == PUT else passenger
    if (row, col) == self.landmarks[target]:
      procedure, action = (PUTDOWN_PROCEDURE, DROPOFF) if subtask == PUT else (PICKUP_PROCEDURE, PICKUP)
    else:
      procedure, action = NAVIGATE[target], self.routes[target][(row, col)]
    self.stack = self._next_stack(subtask, procedure)
    return action, [list(frame) for frame in self.stack]

  def _next_stack(self, subtask: int, procedure: int) -> tuple:
    """The stack-machine step to (Get or Put, procedure): resume the deepest frame that goes on."""
    if self.stack is None:
      return (0, 0), (subtask, 0), (procedure, 0)
    root, middle, lowest = self.stack
    if middle[0] != subtask:
      return (0, root[1] + 1), (subtask, 0), (procedure, 0)
    if lowest[0] != procedure:
      return root, (subtask, middle[1] + 1), (procedure, 0)
    return root, middle, (procedure, lowest[1] + 1)
