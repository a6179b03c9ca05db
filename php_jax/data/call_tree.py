"""A demonstration's call stack read as calls: which procedure ran at each level, from which step to which,
inside which caller, and the elementary actions at the bottom; and as readable text.

A stack [T, d] (procedure and counter per step and level, root first, the demonstration file's and
`decoding.decode`'s layout) holds the calls implicitly: a new call starts at level k on step t when t = 0 or
any level above k changed its frame (procedure or counter) between t−1 and t, since a frame only changes by
issuing its next operation, which pushes fresh calls on every level below it.
"""
from __future__ import annotations

import dataclasses
from typing import Callable, Sequence

import numpy as np


@dataclasses.dataclass(frozen=True)
class Call:
  """One call: level, procedure id, the steps [start, end) it was on the stack, and its callees in order
  (empty at the lowest level, whose steps each took one elementary action)."""
  level: int
  procedure: int
  start: int
  end: int
  callees: tuple[Call, ...] = ()


def call_starts(procedures, counters) -> np.ndarray:
  """[T, d] bool: whether a new call starts at level k on step t (module docstring)."""
  procedures, counters = np.asarray(procedures), np.asarray(counters)
  steps, depth = procedures.shape
  changed = np.zeros((steps, depth), bool)
  changed[1:] = (procedures[1:] != procedures[:-1]) | (counters[1:] != counters[:-1])
  starts = np.zeros((steps, depth), bool)
  starts[:1] = True  # step 0 (if any) starts a call at every level
  for level in range(1, depth):
    starts[:, level] = starts[:, level - 1] | changed[:, level - 1]
  return starts


def calls_per_procedure(procedures, counters, length, num_procs: Sequence[int]) -> list[np.ndarray]:
  """Per level, root first, [K_k] int: how many calls of each procedure the stacks [B, T, d] make over their
  first length [B] steps (a procedure with none is one the stacks never use; unknown frames, −1, are not
  counted)."""
  procedures, counters = np.asarray(procedures), np.asarray(counters)
  counts = [np.zeros(k, int) for k in num_procs]
  for b, n in enumerate(np.asarray(length)):
    starts = call_starts(procedures[b, :n], counters[b, :n])
    for level, count in enumerate(counts):
      called = procedures[b, :n, level][starts[:, level]]
      np.add.at(count, called[called >= 0], 1)
  return counts


def calls(procedures, counters, length: int | None = None) -> Call:
  """The root's call, holding every call below it, of a stack [T, d] over its first length steps (default
  T; −1 entries, unknown or padding, are read as procedure −1). Raises ValueError for stacks that are not
  integer arrays [T, d] of one shape (T ≥ 1), or a length outside 1..T."""
  procedures, counters = np.asarray(procedures), np.asarray(counters)
  for name, x in (("procedures", procedures), ("counters", counters)):
    if x.ndim != 2 or not len(x) or not np.issubdtype(x.dtype, np.integer):
      raise ValueError(f"{name} must be an integer array [T, d] with T ≥ 1; got {x.dtype} of shape {x.shape}")
  if counters.shape != procedures.shape:
    raise ValueError(f"counters must have procedures' shape {procedures.shape}; got {counters.shape}")
  if length is not None and not (isinstance(length, (int, np.integer)) and not isinstance(length, bool)
                                 and 1 <= length <= len(procedures)):
    raise ValueError(f"length must be an integer in 1..T = 1..{len(procedures)}; got {length!r}")
  procedures, counters = procedures[:length], counters[:length]
  starts = call_starts(procedures, counters)
  depth = procedures.shape[1]

  def build(level: int, start: int, end: int) -> Call:
    if level == depth - 1:
      return Call(level, int(procedures[start, level]), start, end)
    below = [t for t in range(start, end) if starts[t, level + 1]] + [end]
    return Call(level, int(procedures[start, level]), start, end,
                tuple(build(level + 1, a, b) for a, b in zip(below[:-1], below[1:])))

  return build(0, 0, len(procedures))


def level_calls(root: Call) -> list[list[Call]]:
  """Every call, per level (root first), in order of their start."""
  found: list[list[Call]] = []

  def visit(call: Call):
    while len(found) <= call.level:
      found.append([])
    found[call.level].append(call)
    for callee in call.callees:
      visit(callee)

  visit(root)
  return found


def run_lengths(names: Sequence[str]) -> str:
  """Consecutive equal names counted: ["E", "E", "E", "pick"] → "E ×3, pick"."""
  parts, i = [], 0
  while i < len(names):
    j = i
    while j < len(names) and names[j] == names[i]:
      j += 1
    parts.append(names[i] if j - i == 1 else f"{names[i]} ×{j - i}")
    i = j
  return ", ".join(parts)


def text(root: Call, procedure_name: Callable[[int, int], str], action_names: Sequence[str]) -> list[str]:
  """The call tree as indented lines, one per call; a lowest-level call's line ends with its actions,
  counted where repeated ("navigate_Y: north ×2, west ×3").

  procedure_name(level, procedure) → its name; action_names: the name of the action at each step."""
  lines = []

  def visit(call: Call, depth: int):
    name = procedure_name(call.level, call.procedure)
    if call.callees:
      lines.append("  " * depth + name)
      for callee in call.callees:
        visit(callee, depth + 1)
    else:
      lines.append("  " * depth + f"{name}: {run_lengths(action_names[call.start:call.end])}")

  visit(root, 0)
  return lines

