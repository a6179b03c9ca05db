"""Problem files (JSON lines) for `experiments.evaluate`: parsing with line-numbered errors."""
from __future__ import annotations

import json

from php_jax.task import Task


class ProblemFileError(ValueError):
  """A malformed problem line; the message starts with 'PATH:LINE:'."""


def read_problems(path: str, task: Task) -> list:
  """All problems of a JSON-lines file (blank lines skipped), parsed by the task. Raises ProblemFileError
  at the first bad line."""
  problems = []
  with open(path, encoding="utf-8") as f:
    for number, line in enumerate(f, start=1):
      if not line.strip():
        continue
      try:
        obj = json.loads(line)
        if not isinstance(obj, dict):
          raise ValueError("a problem must be a JSON object")
        problems.append(task.parse_problem(obj))
      except (ValueError, json.JSONDecodeError) as e:
        raise ProblemFileError(f"{path}:{number}: malformed {task.name} problem: {e}") from None
  return problems
