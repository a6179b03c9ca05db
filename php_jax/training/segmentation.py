"""The loop segmentation: calls read off the demonstrations' actions alone, for joint training without
annotation to start from (`TrainConfig.segment_iterations`).

It rests on two assumptions. (1) An action value that never follows itself in the demonstrations ends the
call it follows (that call's counter goes on); every other value starts a call of the lowest level. (2) A
call of the level above repeats one kind of lowest-level call: consecutive lowest-level calls that start with
the same action value are one call of the level above. On NanoCraft (a loop of moves, then a placement) they
give the supervisor's counters of both levels at every step; where no action value ever follows itself
(addition, bubble sort) the actions show no loops and there is no segmentation.
"""
from __future__ import annotations

import numpy as np

from php_jax.demos import UNKNOWN, Demonstration


def attached_actions(demos: Demonstration) -> set[tuple[int, ...]] | None:
  """The action values (one int per factor) that never follow themselves in demos (assumption 1), or None
  where the actions show no loops: no value follows itself, or every value does."""
  seen, repeated = set(), set()
  for actions, n in zip(np.asarray(demos.actions), np.asarray(demos.length)):
    rows = [tuple(int(a) for a in row) for row in actions[:n]]
    seen.update(rows)
    repeated.update(a for a, b in zip(rows, rows[1:]) if a == b)
  attached = seen - repeated
  return attached if repeated and attached else None


def loop_counters(demos: Demonstration, attached: set[tuple[int, ...]]) -> np.ndarray:
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


def hinted_demonstrations(demos: Demonstration, capacity: tuple[int, ...],
                          attached: set[tuple[int, ...]] | None = None) -> Demonstration | None:
  """demos with each demonstration without annotation given the loop segmentation's counters of the two
  lowest levels below the root (of the lowest alone in a two-level hierarchy) as a partial annotation, every
  procedure and other counter unknown; a counter at or above its level's capacity (root first) stays unknown.
  Annotated demonstrations are kept as they are. attached: assumption (1)'s values (default: demos' own,
  `attached_actions`; another set's, to segment held-out demonstrations as the training ones are). None where
  the actions show no loops."""
  attached = attached_actions(demos) if attached is None else attached
  if attached is None:
    return None
  num_levels = len(capacity)
  counters = loop_counters(demos, attached)[..., -min(2, num_levels - 1):]
  levels = range(num_levels - counters.shape[-1], num_levels)
  counters = np.where(counters < np.asarray([capacity[level] for level in levels]), counters, UNKNOWN)
  strong = np.asarray(demos.strong)
  procedures, all_counters = np.asarray(demos.procedures).copy(), np.asarray(demos.counters).copy()
  procedures[~strong] = UNKNOWN
  all_counters[~strong] = UNKNOWN
  all_counters[~strong, :, levels.start:] = counters[~strong]
  return demos._replace(procedures=procedures, counters=all_counters, strong=np.ones_like(strong))
