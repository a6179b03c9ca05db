"""The tests' commands run several at a time: each is its own process, as `subprocess.run` starts it. A
command refused at its flags spends its seconds importing JAX on one core; the next one takes the other."""
from __future__ import annotations

import concurrent.futures
import json
import os
import subprocess
import sys
from typing import Sequence

from php_jax.envs import gym


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


def fit_recorded(folder, hierarchy: dict, lines: list[dict], *flags: str):
  """Writes hierarchy and `gym.record`'s lines into folder (a pathlib.Path) and runs `experiments.fit` on them
  with flags, its workdir folder/run (without a report); asserts it succeeded and returns the workdir. These fits
  are learning runs, whose running time outweighs their compiling: XLA optimizes them (the setting given last
  in XLA_FLAGS wins over tests/conftest.py's)."""
  folder.mkdir(parents=True, exist_ok=True)
  (folder / "hierarchy.json").write_text(json.dumps(hierarchy))
  gym.write_demonstrations(str(folder / "demos.jsonl"), lines)
  proc = subprocess.run([sys.executable, "-m", "experiments.fit", f"--demos={folder / 'demos.jsonl'}",
                         f"--hierarchy={folder / 'hierarchy.json'}", f"--workdir={folder / 'run'}", "--noreport",
                         *flags], capture_output=True, text=True, timeout=600,
                        env={**os.environ, "XLA_FLAGS": f"{os.environ.get('XLA_FLAGS', '')} "
                                                        "--xla_backend_optimization_level=2"})
  assert proc.returncode == 0, proc.stderr
  return folder / "run"


RECORD_REFUSALS = "PHP_JAX_RECORD_REFUSALS"  # a file: every refusal a test's command gives is appended to it


def record_refusal(command, proc: subprocess.CompletedProcess) -> None:
  """Appends {"test", "command", "refusal"} to the file RECORD_REFUSALS names, if it names one and the command
  was `python -m experiments.X` refused as every command refuses (exit status 2, one line on stderr): the rows of
  docs/bad-inputs.md's generated table (`python docs/refusals.py FILE` writes it). tests/conftest.py calls it
  for every subprocess.run of a test."""
  path = os.environ.get(RECORD_REFUSALS)
  command = [str(part) for part in command] if isinstance(command, (list, tuple)) else []
  stderr = proc.stderr if isinstance(proc.stderr, str) else ""
  if not (path and proc.returncode == 2 and len(command) > 2 and command[1] == "-m"
          and command[2].startswith("experiments.") and len(stderr.strip().splitlines()) == 1):
    return
  test = os.environ.get("PYTEST_CURRENT_TEST", "").split(" ")[0]
  with open(path, "a", encoding="utf-8") as f:
    f.write(json.dumps({"test": test, "command": ["python", *command[1:]], "refusal": stderr.strip()}) + "\n")
