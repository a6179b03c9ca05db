"""BabyAI (package `minigrid`) as a user brings it to php_jax: the levels with MiniGrid's own egocentric view and
the mission read as factors, and BabyAI's own expert, `minigrid.utils.baby_ai_bot.BabyAIBot`, saying the call
stack of every action it takes.

  root -> go_to, pick_up, open, put_next (the mission's own), explore, unlock, unblock
  these -> (some of, babyai.json's "calls") navigate_object, navigate_beside, navigate_explore, navigate_door,
           navigate_key, navigate_cell (left, right, forward); pickup, drop, toggle, done (one action each)

The bot plans with a stack of subgoals, a to-do list rather than a call stack: an instruction pushes all its
subgoals at once, and exploration is planned again at every step. `BabyAIExpert` labels each subgoal, as it is
pushed, with the part of the task it serves (a level-1 procedure), names the level-2 procedure by the subgoal
that chose the action, and turns the sequence of (part, procedure) into call stacks (babyai.json).
A PHP procedure takes no arguments, so each kind of navigation is a procedure of its own, as in DoorKey.
"""
from __future__ import annotations

import contextlib
import io
import re

import gymnasium
import numpy as np
from gymnasium import spaces
from minigrid.core.constants import COLOR_TO_IDX, OBJECT_TO_IDX, STATE_TO_IDX  # registers the levels too
from minigrid.core.world_object import WorldObj
from minigrid.envs.babyai.core.verifier import GoToInstr, ObjDesc, OpenInstr, PickupInstr, PutNextInstr
from minigrid.utils import baby_ai_bot as bot_lib

GO_TO_LOCAL, PICKUP_LOC, UNLOCK_PICKUP = "BabyAI-GoToLocal-v0", "BabyAI-PickupLoc-v0", "BabyAI-UnlockPickup-v0"

PARTS = ("go_to", "pick_up", "open", "put_next", "explore", "unlock", "unblock")  # level 1
PROCEDURES = ("navigate_object", "navigate_beside", "navigate_explore", "navigate_door", "navigate_key",
              "navigate_cell", "pickup", "drop", "toggle", "done")  # level 2
NAVIGATIONS = PROCEDURES[:6]

VERBS = ("go to", "pick up", "open", "put")  # the mission factor's values 0..3
TYPES = ("object", "box", "ball", "key", "door")  # an object type, 1..5 (0: no object)
LOCATIONS = {"": 0, " on your left": 1, " on your right": 2, " in front of you": 3, " behind you": 4}
_COLOURS = sorted(COLOR_TO_IDX, key=COLOR_TO_IDX.get)
_DESCRIPTION = (rf"(?:the|a) (?:({'|'.join(_COLOURS)}) )?({'|'.join(TYPES)})"
                rf"({'|'.join(re.escape(loc) for loc in LOCATIONS if loc)})?")
_ONE_OBJECT = re.compile(rf"(go to|pick up|open) {_DESCRIPTION}")
_TWO_OBJECTS = re.compile(rf"put {_DESCRIPTION} next to {_DESCRIPTION}")
_OBJECT_SIZES = (len(_COLOURS) + 1, len(TYPES) + 1, len(LOCATIONS))
MISSION_SIZES = (len(VERBS), *_OBJECT_SIZES, *_OBJECT_SIZES)


def mission_factors(mission: str) -> list[int]:
  """A one-clause BabyAI mission as 7 factors: the verb (VERBS), then the object's colour (1 + MiniGrid's colour
  index, 0 where the mission names none), type (1 + its index in TYPES, "object" meaning any) and location
  (LOCATIONS), then the same for the second object of "put ... next to ..." (0, 0, 0 where there is none).
  ValueError for a mission of another form."""
  if match := _ONE_OBJECT.fullmatch(mission):
    verb, objects = match[1], (match.groups()[1:], (None, None, None))
  elif match := _TWO_OBJECTS.fullmatch(mission):
    verb, objects = "put", (match.groups()[:3], match.groups()[3:])
  else:
    raise ValueError(f"cannot read the mission {mission!r}: the observation reads one-clause missions (go to, pick "
                     "up, open, put ... next to ...), not sequences of them (, then / after you / and)")

  def described(colour, kind, location):
    if kind is None:
      return [0, 0, 0]
    return [0 if colour is None else COLOR_TO_IDX[colour] + 1, TYPES.index(kind) + 1, LOCATIONS[location or ""]]

  return [VERBS.index(verb), *described(*objects[0]), *described(*objects[1])]


class BabyAIFactors(gymnasium.ObservationWrapper):
  """MiniGrid's own observation as factors: the 7×7 egocentric view's object, colour and state codes (MiniGrid's
  `image[column, row, code]` as entry 3 (7 column + row) + code; the agent stands at column 3, row 6, facing row
  0, with what it carries in its own cell), the direction (entry 147), then the mission (`mission_factors`)."""

  def __init__(self, env: gymnasium.Env):
    super().__init__(env)
    view = env.unwrapped.agent_view_size
    cell = [len(OBJECT_TO_IDX), len(COLOR_TO_IDX), len(STATE_TO_IDX)]
    self.observation_space = spaces.MultiDiscrete(cell * view * view + [4, *MISSION_SIZES])

  def reset(self, **kwargs):
    with contextlib.redirect_stdout(io.StringIO()):  # minigrid prints every layout it rejects while sampling
      return super().reset(**kwargs)

  def observation(self, observation):
    image = np.asarray(observation["image"], np.int64).reshape(-1)
    return np.concatenate([image, [observation["direction"]], mission_factors(observation["mission"])])


def make_env(level: str = GO_TO_LOCAL) -> gymnasium.Env:
  """A BabyAI level with factored observations (the `--env` of record and act; GoToLocal by default)."""
  return BabyAIFactors(gymnasium.make(level))


def make_pickup_loc() -> gymnasium.Env:
  """BabyAI-PickupLoc-v0: pick up an object, maybe named by where it lies (on your left, behind you...)."""
  return make_env(PICKUP_LOC)


def make_unlock_pickup() -> gymnasium.Env:
  """BabyAI-UnlockPickup-v0: pick up a box in the next room, behind a locked door whose key lies nearby."""
  return make_env(UNLOCK_PICKUP)


_MISSION_PARTS = {GoToInstr: "go_to", PickupInstr: "pick_up", OpenInstr: "open", PutNextInstr: "put_next"}


class _Plan(list):
  """The bot's subgoal stack, labelling each subgoal with its part (`subgoal.part`) when pushed: the pushes a
  subgoal makes while it plans are labelled together, from what they are and who pushed them."""

  def __init__(self, subgoals: list, part: str):
    super().__init__()
    self.pushed = []
    for subgoal in subgoals:
      self.append(subgoal)
      subgoal.part = part

  def append(self, subgoal):
    super().append(subgoal)
    self.pushed.append(subgoal)
    for name in ("replan_before_action", "replan_after_action"):
      setattr(subgoal, name, self._traced(subgoal, getattr(subgoal, name)))

  def _traced(self, pusher, method):
    def run(*args):
      self.pushed = []
      suggested = method(*args)
      if self.pushed:
        self._label(pusher, self.pushed)
      return suggested
    return run

  def _label(self, pusher, pushed: list) -> None:
    """Labels the subgoals pusher has just pushed (the top of the stack) with one part."""
    if any(isinstance(s, bot_lib.GoNextToSubgoal) and isinstance(s.datum, ObjDesc) and s.datum.type == "key"
           for s in pushed):  # a door to open is locked: fetch its key, open it, put the key down
      part = "unlock"
      if isinstance(pusher, bot_lib.GoNextToSubgoal):  # it went to the door for the OpenSubgoal just below
        self[-len(pushed) - 1].part = part
    elif isinstance(pusher, bot_lib.ExploreSubgoal) or any(s.is_exploratory() for s in pushed):
      part = "explore"
    elif isinstance(pusher, bot_lib.GoNextToSubgoal) and any(isinstance(s, bot_lib.DropSubgoal) for s in pushed):
      part = "unblock"  # an object is in the way: it is moved aside
    else:
      part = pusher.part
    for subgoal in pushed:
      subgoal.part = part


class BabyAIExpert:
  """BabyAI's bot (`minigrid.utils.baby_ai_bot.BabyAIBot`), acting as it does, with the call stack of every
  action: [[root, τ], [a part (babyai.json's level 1), τ], [a procedure (level 2), τ]].

  A level-1 call lasts while the bot works for the same part, a navigation call while it navigates the same
  way in it; pickup, drop, toggle and done are calls of one action. The bot's `done` (its plan is empty) is
  the mission's part calling `done`."""

  def __init__(self, env: gymnasium.Env):
    self.env = env
    self.bot = self.mission_part = self.stack = None

  def reset(self, observation, info) -> None:
    instruction = self.env.unwrapped.instrs
    if type(instruction) not in _MISSION_PARTS:
      raise ValueError(f"the mission {self.env.unwrapped.mission!r} is not one clause (go to, pick up, open, put "
                       "... next to ...)")
    self.mission_part = _MISSION_PARTS[type(instruction)]
    self.bot = bot_lib.BabyAIBot(self.env)
    self.bot.stack = _Plan(self.bot.stack, self.mission_part)
    self.stack = None

  def act(self, observation, info):
    action = int(self.bot.replan())
    subgoal = self.bot.stack[-1] if self.bot.stack else None
    part = subgoal.part if subgoal else self.mission_part
    self.stack = self._next_stack(part, self._procedure(subgoal))
    return action, [list(frame) for frame in self.stack]

  def _procedure(self, subgoal) -> str:
    """The level-2 procedure the subgoal that chose the action stands for."""
    if subgoal is None:
      return "done"
    if isinstance(subgoal, bot_lib.PickupSubgoal):
      return "pickup"
    if isinstance(subgoal, bot_lib.DropSubgoal):
      return "drop"
    if isinstance(subgoal, (bot_lib.OpenSubgoal, bot_lib.CloseSubgoal)):
      return "toggle"
    if subgoal.is_exploratory():
      return "navigate_explore"
    instruction, datum = self.env.unwrapped.instrs, subgoal.datum
    if isinstance(datum, ObjDesc):  # the mission's objects, or the key of a locked door
      if datum is getattr(instruction, "desc_fixed", None):
        return "navigate_beside"
      if any(datum is getattr(instruction, name, None) for name in ("desc", "desc_move")):
        return "navigate_object"
      return "navigate_key"
    if isinstance(datum, WorldObj):  # the bot names doors it opens by reference
      return "navigate_door"
    return "navigate_cell"

  def _next_stack(self, part: str, procedure: str) -> tuple:
    """The call-stack step to (part, procedure): the deepest level that goes on resumes, the ones below start."""
    part_id, procedure_id = PARTS.index(part), PROCEDURES.index(procedure)
    if self.stack is None:
      return (0, 0), (part_id, 0), (procedure_id, 0)
    root, middle, lowest = self.stack
    if middle[0] != part_id:
      return (0, root[1] + 1), (part_id, 0), (procedure_id, 0)
    if lowest[0] != procedure_id or procedure not in NAVIGATIONS:
      return root, (part_id, middle[1] + 1), (procedure_id, 0)
    return root, middle, (procedure_id, lowest[1] + 1)
