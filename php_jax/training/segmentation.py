"""Segmentations read off the demonstrations' actions alone: calls as a partial annotation for joint training
without annotation to start from (`TrainConfig.segment_iterations`), by one of two rules
(`TrainConfig.segment_rule`).

"loops" rests on two assumptions. (1) An action value that never follows itself in the demonstrations ends
the call it follows (that call's counter goes on); every other value starts a call of the lowest level. (2) A
call of the level above repeats one kind of lowest-level call: consecutive lowest-level calls that start with
the same action value are one call of the level above. On NanoCraft (a loop of moves, then a placement) they
give the supervisor's counters of both levels at every step. It applies where some action value follows
itself and another never does.

"successors": an action continues the lowest-level call of the action before it when that value is always
followed by the same value in the demonstrations (a fixed sequence of actions is one call); the level above
stays unknown. On bubble sort every call it starts is the supervisor's, but `dece` and the `lshift` always
after it are one call; on addition it cuts `lshift` in two, after the move it shares with `carry`. It
applies where some action value has one successor.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from php_jax.demos import UNKNOWN, Demonstration

Action = tuple[int, ...]  # one elementary action: one int per factor


class Rule(NamedTuple):
  """A segmentation rule read off training demonstrations. name: "loops" or "successors"; actions: the values
  it reads (loops: those that never follow themselves; successors: those always followed by one value)."""
  name: str
  actions: frozenset[Action]


def _action_rows(demos: Demonstration):
  for actions, n in zip(np.asarray(demos.actions), np.asarray(demos.length)):
    yield [tuple(int(a) for a in row) for row in actions[:n]]


def attached_actions(demos: Demonstration) -> set[Action] | None:
  """The action values that never follow themselves in demos (the loops rule's assumption 1), or None where
  the actions show no loops: no value follows itself, or every value does."""
  seen, repeated = set(), set()
  for rows in _action_rows(demos):
    seen.update(rows)
    repeated.update(a for a, b in zip(rows, rows[1:]) if a == b)
  attached = seen - repeated
  return attached if repeated and attached else None


def single_successor_actions(demos: Demonstration) -> set[Action]:
  """The action values always followed by one and the same value in demos (the end of a demonstration counts
  as a successor)."""
  successors: dict[Action, set] = {}
  for rows in _action_rows(demos):
    for a, b in zip(rows, rows[1:] + [None]):
      successors.setdefault(a, set()).add(b)
  return {a for a, following in successors.items() if len(following) == 1}


RULES = ("loops", "successors")
UNSEGMENTED = {"loops": "no action value follows itself, or every one does",  # why a rule does not apply
               "successors": "no action value is always followed by the same one"}


def read_rule(demos: Demonstration, name: str) -> Rule | None:
  """The segmentation rule `name` (one of RULES) read off demos' actions, or None where it does not apply."""
  if name == "loops":
    attached = attached_actions(demos)
    return None if attached is None else Rule(name, frozenset(attached))
  single = single_successor_actions(demos)
  return Rule(name, frozenset(single)) if single else None


def loop_counters(demos: Demonstration, attached: set[Action]) -> np.ndarray:
  """[B, T, 2] int32: each step's counters in the loop segmentation with `attached` as assumption (1)'s
  values: the level above the lowest's, then the lowest's (UNKNOWN on padding)."""
  actions, lengths = np.asarray(demos.actions), np.asarray(demos.length)
  counters = np.full(actions.shape[:2] + (2,), UNKNOWN, np.int32)
  for b, n in enumerate(lengths):
    first = None  # the action that started the current lowest-level call
    for t in range(n):
      action = tuple(int(a) for a in actions[b, t])
      if t > 0 and action in attached:
        counters[b, t] = counters[b, t - 1, 0], counters[b, t - 1, 1] + 1
      else:
        counters[b, t] = (counters[b, t - 1, 0] + 1 if action == first else 0), 0
        first = action
  return counters


def successor_counters(demos: Demonstration, single: set[Action]) -> np.ndarray:
  """[B, T, 2] int32: each step's counters in the successor segmentation with `single` as the values that
  have one successor: the level above the lowest's (UNKNOWN), then the lowest's (UNKNOWN on padding)."""
  counters = np.full(np.shape(demos.actions)[:2] + (2,), UNKNOWN, np.int32)
  for b, rows in enumerate(_action_rows(demos)):
    for t in range(len(rows)):
      counters[b, t, 1] = counters[b, t - 1, 1] + 1 if t > 0 and rows[t - 1] in single else 0
  return counters


def segment_counters(demos: Demonstration, rule: Rule) -> np.ndarray:
  """[B, T, 2] int32: the counters of the level above the lowest and of the lowest that rule reads off demos'
  actions (UNKNOWN where it says nothing, and on padding)."""
  if rule.name == "loops":
    return loop_counters(demos, set(rule.actions))
  return successor_counters(demos, set(rule.actions))


def hinted_demonstrations(demos: Demonstration, capacity: tuple[int, ...],
                          rule: Rule | str = "loops") -> Demonstration | None:
  """demos with each demonstration without annotation given the segmentation's counters of the two lowest
  levels below the root (of the lowest alone in a two-level hierarchy) as a partial annotation, every
  procedure and other counter unknown; a counter at or above its level's capacity (root first) stays unknown.
  Annotated demonstrations are kept as they are. rule: a rule's name (read off demos, `read_rule`), or a
  Rule read off another set, to segment held-out demonstrations as the training ones are. None where the
  rule does not apply."""
  rule = read_rule(demos, rule) if isinstance(rule, str) else rule
  if rule is None:
    return None
  num_levels = len(capacity)
  counters = segment_counters(demos, rule)[..., -min(2, num_levels - 1):]
  levels = range(num_levels - counters.shape[-1], num_levels)
  counters = np.where(counters < np.asarray([capacity[level] for level in levels]), counters, UNKNOWN)
  strong = np.asarray(demos.strong)
  procedures, all_counters = np.asarray(demos.procedures).copy(), np.asarray(demos.counters).copy()
  procedures[~strong] = UNKNOWN
  all_counters[~strong] = UNKNOWN
  all_counters[~strong, :, levels.start:] = counters[~strong]
  return demos._replace(procedures=procedures, counters=all_counters, strong=np.ones_like(strong))
