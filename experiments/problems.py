"""Problem files (JSON lines) for `experiments.evaluate`: parsing with line-numbered errors."""
from __future__ import annotations

import json

from php_jax.envs import nanocraft


class ProblemFileError(ValueError):
  """A malformed problem line; the message starts with 'PATH:LINE:'."""


def _addition(obj: dict) -> tuple[str, str]:
  a, b = obj.get("a"), obj.get("b")
  if not isinstance(a, str) or not isinstance(b, str):
    raise ValueError('needs string fields "a" and "b"')
  if not (a.isascii() and a.isdigit() and b.isascii() and b.isdigit()):
    raise ValueError(f'"a" and "b" must be non-empty strings of decimal digits; got {a!r}, {b!r}')
  if len(a) != len(b):
    raise ValueError(f'"a" and "b" must have the same number of digits; got {len(a)} and {len(b)}')
  return a, b


def _is_int(x) -> bool:
  return isinstance(x, int) and not isinstance(x, bool)


def _nanocraft(obj: dict) -> tuple[int, int, int, int, list]:
  spec = [obj.get(k) for k in ("x", "y", "w", "h")]
  if not all(_is_int(v) for v in spec):
    raise ValueError('needs integer fields "x", "y", "w", "h"')
  x, y, w, h = spec
  preplaced = obj.get("preplaced", [])
  if not isinstance(preplaced, list):
    raise ValueError('"preplaced" must be a list of [row, col] pairs')
  for cell in preplaced:
    if not (isinstance(cell, list) and len(cell) == 2 and all(_is_int(v) for v in cell)):
      raise ValueError(f'"preplaced" entries must be [row, col] integer pairs; got {cell!r}')
  if len({tuple(c) for c in preplaced}) != len(preplaced):
    raise ValueError('"preplaced" lists a cell twice')
  nanocraft.make_problem(x, y, w, h, preplaced)  # raises if the building or a cell does not fit
  return x, y, w, h, preplaced


PARSERS = {"addition": _addition, "nanocraft": _nanocraft}


def read_problems(path: str, task: str) -> list:
  """All problems of a JSON-lines file (blank lines skipped). Raises ProblemFileError at the first bad line."""
  parse = PARSERS[task]
  problems = []
  with open(path, encoding="utf-8") as f:
    for number, line in enumerate(f, start=1):
      if not line.strip():
        continue
      try:
        obj = json.loads(line)
        if not isinstance(obj, dict):
          raise ValueError("a problem must be a JSON object")
        problems.append(parse(obj))
      except (ValueError, json.JSONDecodeError) as e:
        raise ProblemFileError(f"{path}:{number}: malformed {task} problem: {e}") from None
  return problems
