"""The tests' commands run several at a time: each is its own process, as `subprocess.run` starts it. A
command refused at its flags spends its seconds importing JAX on one core; the next one takes the other."""
from __future__ import annotations

import concurrent.futures
import os
import subprocess
from typing import Sequence


def run_all(commands: Sequence[Sequence[str]], **kwargs) -> list[subprocess.CompletedProcess]:
  """subprocess.run(command, **kwargs) for each of commands, as many at a time as there are CPUs: the
  completed processes, in the order of commands."""
  with concurrent.futures.ThreadPoolExecutor(max_workers=os.cpu_count() or 1) as pool:
    return list(pool.map(lambda command: subprocess.run(command, **kwargs), commands))
