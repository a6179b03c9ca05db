"""Problem files (JSON lines) for `experiments.evaluate`: parsing with line-numbered errors."""
from __future__ import annotations

from php_jax.data import json_lines
from php_jax.envs.task import Task


class ProblemFileError(ValueError):
  """A malformed problem line (the message starts with 'PATH:LINE:'), or a file without problems."""


def read_problems(path: str, task: Task) -> list:
  """All problems of a JSON-lines file (blank lines skipped), parsed by the task. Raises ProblemFileError
  at the first bad line (not UTF-8, not JSON within php_jax.data.json_lines' bounds, not a problem), or naming the
  file if it holds no problem."""
  problems = []
  with open(path, "rb") as f:
    for number, raw in json_lines.lines(f):
      try:
        obj = json_lines.loads(raw)
        if not isinstance(obj, dict):
          raise ValueError("a problem must be a JSON object")
        problems.append(task.parse_problem(obj))
      except UnicodeDecodeError as e:
        raise ProblemFileError(f"{path}:{number}: not UTF-8 text ({e.reason} at byte {e.start})") from None
      except ValueError as e:
        raise ProblemFileError(f"{path}:{number}: malformed {task.name} problem: {e}") from None
  if not problems:
    raise ProblemFileError(f"no problems in {path}")
  return problems
