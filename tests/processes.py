"""The tests' commands run several at a time: each is its own process, as `subprocess.run` starts it. A
command refused at its flags spends its seconds importing JAX on one core; the next one takes the other."""
from __future__ import annotations

import concurrent.futures
import json
import os
import subprocess
import sys
from typing import Sequence


def run_all(commands: Sequence[Sequence[str]], **kwargs) -> list[subprocess.CompletedProcess]:
  """subprocess.run(command, **kwargs) for each of commands, as many at a time as there are CPUs: the
  completed processes, in the order of commands."""
  with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
    return list(pool.map(lambda command: subprocess.run(command, **kwargs), commands))


def assert_refused(cases: Sequence[tuple[Sequence[str], str]], timeout: float = 600) -> None:
  """Runs `python -m ARGS` for each (ARGS, message) of cases, as run_all does, and asserts each was refused:
  exit status 2 and one line on stderr holding message."""
  procs = run_all([[sys.executable, "-m", *args] for args, _ in cases], capture_output=True, text=True,
                  timeout=timeout)
  for (args, message), proc in zip(cases, procs):
    assert proc.returncode == 2 and message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, (
        args, proc.stderr)
  _record(cases, procs)


RECORD_REFUSALS = "PHP_JAX_RECORD_REFUSALS"  # a file: each refusal assert_refused checks is appended to it


def _record(cases, procs) -> None:
  """Appends {"test", "command", "refusal"} per case to the file RECORD_REFUSALS names, if it names one: the
  rows of docs/bad-inputs.md's generated table (`python docs/refusals.py FILE` writes it)."""
  path = os.environ.get(RECORD_REFUSALS)
  if not path:
    return
  test = os.environ.get("PYTEST_CURRENT_TEST", "").split(" ")[0]
  with open(path, "a", encoding="utf-8") as f:
    for (args, _), proc in zip(cases, procs):
      f.write(json.dumps({"test": test, "command": ["python", "-m", *map(str, args)],
                          "refusal": proc.stderr.strip()}) + "\n")
