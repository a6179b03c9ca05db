r"""Runs a training experiment over a grid of flag values, one workdir per combination.

  python -m experiments.sweep --task=NAME --workdir=runs/sweep \
      --grid=num_demos=16,32,64 --grid=num_strong=1,2,4,8,16,32,64 --grid=seed=1,2,3,4,5 -- --iterations=2000
  python -m experiments.sweep --task=NAME --workdir=runs/hparams \
      --grid=num_demos=64 --grid=num_strong=8 --grid='tau_in_termination=1,1,1|1,0,1|1,1,0' --grid=seed=1

Each combination runs `python -m experiments.train --task=NAME --workdir=WORKDIR/<name=value,...> --name=value ...`
followed by the flags after `--` (the same for every run). A combination whose results.json exists is
skipped, so an interrupted sweep resumes where it stopped (and a run interrupted mid-way resumes from its
own checkpoint); combinations with num_strong > num_demos are left out. `python -m experiments.plot` reads
the results.
"""
from __future__ import annotations

import concurrent.futures
import itertools
import os
import subprocess
import sys

from absl import app, flags

from experiments import cli

_TASK = flags.DEFINE_string("task", None, "The task trained (what experiments.train --task takes).")
_WORKDIR = flags.DEFINE_string("workdir", None, "Parent directory of the runs' workdirs.")
_GRID = flags.DEFINE_multi_string("grid", [], "name=v1,v2,...: a flag of the experiment and its values.")
_PARALLEL = flags.DEFINE_integer("parallel", 1, "Runs at a time.", lower_bound=1)


def parse_grid(entries: list[str]) -> list[dict[str, str]]:
  """['a=1,2', 'b=x'] → [{'a': '1', 'b': 'x'}, {'a': '2', 'b': 'x'}], without num_strong > num_demos.
  Values that are themselves lists are separated by '|' instead: 'tau_in_termination=1,1,1|1,0,1'. Raises
  ValueError naming the --grid entry that is not name=values, names a flag twice or the sweep's own
  (--task, --workdir), has an empty value, or a num_demos / num_strong value that is not an integer."""
  axes, names = [], set()
  for entry in entries:
    name, sep, values = entry.partition("=")
    if not sep or not name.isidentifier() or not values:
      raise ValueError(f"--grid={entry!r}: expected name=value[,value...] or name=list[|list...]")
    if name in names or name in ("task", "workdir"):
      raise ValueError(f"--grid={entry!r}: --{name} is " + ("given twice" if name in names else "the sweep's own"))
    names.add(name)
    axis = values.split("|" if "|" in values else ",")
    if not all(axis):
      raise ValueError(f"--grid={entry!r}: an empty value")
    if name in ("num_demos", "num_strong") and not all(v.isdigit() for v in axis):
      raise ValueError(f"--grid={entry!r}: {name} values must be non-negative integers")
    axes.append([(name, v) for v in axis])
  combos = [dict(c) for c in itertools.product(*axes)]
  return [c for c in combos
          if not ("num_strong" in c and "num_demos" in c and int(c["num_strong"]) > int(c["num_demos"]))]


def run_name(combo: dict[str, str]) -> str:
  """{'num_demos': '64', 'tau_in_termination': '1,0,1'} → 'num_demos=64,tau_in_termination=1:0:1'."""
  return ",".join(f"{k}={v.replace(',', ':')}" for k, v in combo.items()) or "default"


def _run(task: str, workdir: str, combo: dict[str, str], extra: list[str]) -> tuple[str, int]:
  os.makedirs(workdir, exist_ok=True)
  command = [sys.executable, "-m", "experiments.train", f"--task={task}", f"--workdir={workdir}",
             *(f"--{k}={v}" for k, v in combo.items()), *extra]
  with open(os.path.join(workdir, "stdout.log"), "a") as out:
    return workdir, subprocess.run(command, stdout=out, stderr=subprocess.STDOUT).returncode


def main(argv):
  extra = argv[1:]
  try:
    combos = parse_grid(_GRID.value)
  except ValueError as e:
    cli.fail(str(e))
  if os.path.exists(_WORKDIR.value) and not os.path.isdir(_WORKDIR.value):
    cli.fail(f"--workdir={_WORKDIR.value} is a file, not a directory")
  todo = [(os.path.join(_WORKDIR.value, run_name(c)), c) for c in combos]
  todo = [(w, c) for w, c in todo if not os.path.isfile(os.path.join(w, "results.json"))]
  print(f"{len(combos)} runs, {len(combos) - len(todo)} already done, {len(todo)} to run", flush=True)
  failed = []
  with concurrent.futures.ThreadPoolExecutor(_PARALLEL.value) as pool:
    for workdir, code in pool.map(lambda wc: _run(_TASK.value, wc[0], wc[1], extra), todo):
      print(f"{'done' if code == 0 else f'FAILED (exit {code})'}: {workdir}", flush=True)
      if code:
        failed.append(workdir)
  if failed:
    print(f"{len(failed)} runs failed; see stdout.log in: {', '.join(failed)}", file=sys.stderr)
    sys.exit(1)


if __name__ == "__main__":
  flags.mark_flags_as_required(["task", "workdir"])
  app.run(main, flags_parser=cli.parse_flags)
