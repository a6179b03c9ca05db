"""Which demonstrations to annotate: a ranking of the actions-only ones by what annotating them would add.

An annotation teaches the hierarchy which procedure takes which operation, and with `--call_graph` it also
bounds what each procedure may take: an operation that no annotated demonstration shows is, for the
procedure that should take it, locked out. So the annotated demonstrations should together show every kind
of behaviour the data holds, and as much of it as they can: long demonstrations, whose calls run their
full course, teach more than short or unusual ones (measured on NanoCraft: RESULTS.md, "Which
demonstrations to annotate"). Without a model, a demonstration's behaviour is read off its elementary
actions: the action values it takes and the pairs of consecutive actions (a procedure's operations show up
as such pairs: MOVE_DOWN then PLACE_BLOCK is a different routine from MOVE_DOWN then MOVE_DOWN). The choice is
greedy: while some behaviour that the demonstrations show is shown by no annotated or earlier chosen one,
the next is the longest demonstration that shows some of it; after that, the longest of the others. Given a
trained hierarchy, its uncertainty ranks instead of the length: the demonstration's summed entropy of the
posterior over each level's procedures (nats, over its steps), what the model least knows how to segment.
"""
from __future__ import annotations

import dataclasses
from typing import Callable

import numpy as np

from php_jax.analysis import decoding
from php_jax.demos import Demonstration
from php_jax.hierarchy import check_size
from php_jax.model import PHPHierarchy


@dataclasses.dataclass(frozen=True)
class Suggestion:
  """One demonstration to annotate: its index in the batch, its score (the rarity-weighted behaviour it adds,
  plus its uncertainty where a model was given) and why, in words."""
  index: int
  score: float
  why: str


def behaviours(actions: np.ndarray, length: int) -> set[tuple]:
  """What one demonstration's actions [T, F] show over its first length steps: ("action", a) for each action
  taken and ("pair", a, b) for each action b right after a (actions as tuples of factor values)."""
  taken = [tuple(int(v) for v in a) for a in np.asarray(actions)[:length]]
  return {("action", a) for a in taken} | {("pair", a, b) for a, b in zip(taken[:-1], taken[1:])}


def uncertainty(hierarchy: PHPHierarchy, capacity, demos: Demonstration) -> np.ndarray:
  """[B] the mean over steps of the summed entropy (nats) of each level's posterior over its procedures."""
  _, marginals = decoding.explain(hierarchy, capacity, demos)
  length = np.asarray(demos.length)
  total = np.zeros(len(length))
  for m in marginals[1:]:  # the root level has one procedure
    p = np.clip(m, 1e-12, 1.0)
    total += (-(m * np.log(p)).sum(-1)).sum(-1)
  return total / np.maximum(length, 1)


def suggest(demos: Demonstration, budget: int, action_name: Callable[[list[int]], str] = str,
            certainty_of: np.ndarray | None = None) -> list[Suggestion]:
  """Up to budget of the batch's demonstrations [B, ...] not yet annotated (demos.strong), best first
  (module docstring). certainty_of: optional [B] mean uncertainty per step (`uncertainty`); the score is
  then the summed uncertainty, else the number of steps. Raises ValueError for a budget that is not an
  integer ≥ 0 or a certainty_of that is not [B]."""
  check_size("budget", budget, 0)
  length = np.asarray(demos.length)
  if certainty_of is not None and np.shape(certainty_of) != length.shape:
    raise ValueError(f"certainty_of must be [B] = {list(length.shape)} (one per demonstration); got shape "
                     f"{list(np.shape(certainty_of))}")
  shown = [behaviours(a, n) for a, n in zip(np.asarray(demos.actions), length)]
  counts: dict[tuple, int] = {}
  for kinds in shown:
    for kind in kinds:
      counts[kind] = counts.get(kind, 0) + 1
  worth = length.astype(float) if certainty_of is None else np.asarray(certainty_of) * length
  covered = set().union(*(shown[b] for b in np.flatnonzero(np.asarray(demos.strong))))
  left = [b for b in range(len(length)) if not demos.strong[b]]
  chosen = []
  while left and len(chosen) < budget:
    adding = [b for b in left if shown[b] - covered] or left
    best = max(adding, key=lambda b: (round(float(worth[b]), 9), -b))
    new = sorted(shown[best] - covered, key=lambda k: (counts[k], str(k)))
    doubt = None if certainty_of is None else float(certainty_of[best])
    why = _why(new, counts, len(length), length[best], action_name, doubt)
    chosen.append(Suggestion(best, round(float(worth[best]), 6), why))
    covered |= shown[best]
    left.remove(best)
  return chosen


def _why(new: list[tuple], counts: dict, total: int, length: int, action_name, doubt) -> str:
  """In words: the demonstration's length and what it shows that no annotated or earlier chosen one shows
  (new: those behaviours, rarest first; counts: in how many of the total demonstrations each is)."""
  if not new:
    text = (f"{length} steps, the {'longest' if doubt is None else 'most uncertain'} left: every action and pair "
            "of consecutive actions in it is shown already by the annotated or earlier chosen demonstrations")
  else:
    actions = [_named(k, action_name) for k in new if k[0] == "action"]
    pairs = len(new) - len(actions)
    parts = ([f"{len(actions)} action{'s' if len(actions) > 1 else ''} ({', '.join(actions)})"] if actions else []
             ) + ([f"{pairs} pair{'s' if pairs > 1 else ''} of consecutive actions"] if pairs else [])
    rare = ", ".join(f"{_named(k, action_name)} (in {counts[k]} of the {total} demonstrations)" for k in new[:3])
    text = (f"{length} steps; shows {' and '.join(parts)} that no annotated or earlier chosen demonstration "
            f"shows, the rarest {rare}")
  if doubt is not None:
    text += f"; the model's uncertainty about its segmentation: {doubt:.2f} nats per step"
  return text


def _named(kind: tuple, action_name) -> str:
  if kind[0] == "action":
    return action_name(list(kind[1]))
  return f"{action_name(list(kind[1]))} → {action_name(list(kind[2]))}"
