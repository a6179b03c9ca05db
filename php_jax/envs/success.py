"""When an episode in a Gymnasium environment counts as a success.

Gymnasium does not define success, and ending an episode is not it: FrozenLake ends in a hole, a lander ends
crashed and BabyAI ends a failed mission as surely as a solved one. A success rule says what success is, in
the text the `--success` flag takes:

  info:KEY     the info the environment gave with the episode's last step holds a true KEY
  return>X     the episode's return is above X (also return>=X)
  reward>X     the last step's reward is above X (also reward>=X); BabyAI's own rule is reward>0
  terminated   the episode reached a terminal state of the environment (Gymnasium's `terminated`, also where its
               time limit truncated the same step), not one only truncated or ended by the policy

Without a rule, episodes of which any reports `info["is_success"]` with its last step are judged by
info:is_success (those that do not report it count as failures, and the summary says how many); otherwise
success is unknown (None), never guessed.
"""
from __future__ import annotations

import operator
import re
from typing import Any, NamedTuple

import numpy as np

DEFAULT_KEY = "is_success"
HOW_TO_DEFINE = "--success=info:KEY, return>X, reward>X or terminated defines it"


class SuccessRule(NamedTuple):
  """A parsed rule: kind is "info", "return", "reward" or "terminated"; key the info key (kind "info");
  threshold and inclusive (>= rather than >) the bound (kinds "return" and "reward")."""
  kind: str
  key: str | None = None
  threshold: float | None = None
  inclusive: bool = False

  def __str__(self) -> str:
    if self.kind == "info":
      return f"info:{self.key}"
    if self.kind == "terminated":
      return "terminated"
    return f"{self.kind}{'>=' if self.inclusive else '>'}{self.threshold:g}"


class Ending(NamedTuple):
  """How one episode ended: its return, its last step's reward (None without a step), whether the environment
  terminated or truncated it, and the info the environment gave with its last step (or at reset)."""
  episode_return: float
  last_reward: float | None
  terminated: bool
  truncated: bool
  info: dict[str, Any]


_BOUND = re.compile(r"^(return|reward)(>=|>)([-+]?(\d+\.?\d*|\.\d+)([eE][-+]?\d+)?)$")


def parse(text: str) -> SuccessRule:
  """The rule that text writes (see the module's docstring). Raises ValueError naming the text otherwise."""
  text = text.strip()
  if text == "terminated":
    return SuccessRule("terminated")
  if text.startswith("info:") and text[5:].strip():
    return SuccessRule("info", key=text[5:].strip())
  match = _BOUND.match(text.replace(" ", ""))
  if match:
    return SuccessRule(match[1], threshold=float(match[3]), inclusive=match[2] == ">=")
  raise ValueError(f"--success={text!r} is not a success rule: use info:KEY, return>X, return>=X, reward>X, "
                   "reward>=X or terminated")


def rule_in_force(rule: SuccessRule | None, endings: list[Ending]) -> SuccessRule | None:
  """The rule that judges these episodes: the one given; without one, info:is_success where any episode's last
  info reported it; else None (success unknown)."""
  if rule is not None:
    return rule
  if any(DEFAULT_KEY in e.info for e in endings):
    return SuccessRule("info", key=DEFAULT_KEY)
  return None


def judge(rule: SuccessRule | None, ending: Ending) -> bool | None:
  """Whether the episode succeeded under rule (None for no rule: unknown)."""
  if rule is None:
    return None
  if rule.kind == "info":
    return _true(ending.info.get(rule.key, False))
  if rule.kind == "terminated":
    return ending.terminated
  value = ending.episode_return if rule.kind == "return" else ending.last_reward
  compare = operator.ge if rule.inclusive else operator.gt
  return value is not None and bool(compare(value, rule.threshold))


def _true(value) -> bool:
  """Whether an info value says yes: true, or an array whose every entry is (an empty one or a NaN does not)."""
  value = np.asarray(value)
  if value.size == 0 or (np.issubdtype(value.dtype, np.floating) and np.isnan(value).any()):
    return False
  return bool(np.all(value))


def judge_all(rule: SuccessRule | None, endings: list[Ending]) -> tuple[SuccessRule | None, list[bool | None]]:
  """(the rule in force, each episode's success under it)."""
  rule = rule_in_force(rule, endings)
  return rule, [judge(rule, e) for e in endings]


def summary(given: SuccessRule | None, endings: list[Ending]) -> list[str]:
  """The lines a command prints about its episodes: the success rate and its rule, or why it is unknown; then
  the mean return and how the episodes ended, each counted once (terminated, also where the time limit
  truncated the same step; truncated only; neither: by the policy). No episodes: one line saying so."""
  if not endings:
    return ["no episodes"]
  rule, successes = judge_all(given, endings)
  count = len(endings)
  if rule is None:
    first = f"success unknown: no episode's last step reported info[\"{DEFAULT_KEY}\"]; " + HOW_TO_DEFINE
  else:
    first = f"success {sum(successes) / count:.3f} ({rule})"
    reported = sum(rule.key in e.info for e in endings) if given is None else count
    if reported < count:
      first += (f"; {count - reported} of {count} episodes did not report it and count as failures: "
                + HOW_TO_DEFINE)
  terminated = sum(e.terminated for e in endings)
  truncated = sum(e.truncated and not e.terminated for e in endings)
  by_policy = sum(not (e.terminated or e.truncated) for e in endings)
  returns = sum(e.episode_return for e in endings) / count
  ends = f"{terminated} terminated, {truncated} truncated" + (f", {by_policy} ended by the policy" if by_policy else "")
  return [first, f"mean return {returns:.2f}; {ends}"]
