r"""Runs a training experiment over a grid of flag values, one workdir per combination.

  python -m experiments.sweep --task=NAME --workdir=runs/sweep \
      --grid=num_demos=16,32,64 --grid=num_strong=1,2,4,8,16,32,64 --grid=seed=1,2,3,4,5 -- --iterations=2000
  python -m experiments.sweep --task=NAME --workdir=runs/sweep \
      --grid=num_demos=16,32,64 --grid=num_strong=1,2,4,8,16,32,64 --seeds=1,2,3,4,5
  python -m experiments.sweep --task=NAME --workdir=runs/hparams \
      --grid=num_demos=64 --grid=num_strong=8 --grid='tau_in_termination=1,1,1|1,0,1|1,1,0' --grid=seed=1

Each combination runs `python -m experiments.train --task=NAME --workdir=WORKDIR/<name=value,...> --name=value
...` followed by the flags after `--` (the same for every run). A combination whose results.json exists (with
--seeds, every seed's) is skipped, so an interrupted sweep resumes where it stopped (and a run interrupted
mid-way resumes from its own checkpoint); combinations with num_strong > num_demos are left out. `python -m
experiments.plot` reads the results.

With --seeds=1,2,3,4,5 each combination trains those seeds as one program (`experiments.train --seeds`), its
workdir holding one seed=S workdir per seed: the paper's grid is then 18 runs instead of 90, each level
compiled once for its 5 trials.

With --gpus=0,1,...: --parallel runs at a time on each of those GPUs, each run seeing only its own
(CUDA_VISIBLE_DEVICES) and allocating GPU memory as it goes (XLA_PYTHON_CLIENT_PREALLOCATE=false), so that
runs sharing a GPU do not each reserve most of it.
"""
from __future__ import annotations

import concurrent.futures
import ctypes
import itertools
import os
import queue
import shutil
import signal
import subprocess
import sys
import time
from typing import Callable, Iterator, TypeVar

from absl import app, flags

from experiments.common import cli
from php_jax.envs import tasks

_TASK = flags.DEFINE_string("task", None, "The task trained (what experiments.train --task takes).")
_WORKDIR = flags.DEFINE_string("workdir", None, "Parent directory of the runs' workdirs.")
_GRID = flags.DEFINE_multi_string("grid", [], "name=v1,v2,...: a flag of the experiment and its values.")
_PARALLEL = flags.DEFINE_integer("parallel", 1, "Runs at a time (with --gpus, on each GPU).", lower_bound=1,
                                 upper_bound=1024)
_GPUS = flags.DEFINE_list("gpus", None, "GPUs to run on (CUDA's ids, as CUDA_VISIBLE_DEVICES takes them): each run "
                          "gets one of them alone, --parallel runs per GPU. Default: every run sees this process's "
                          "devices.")
_SEEDS = flags.DEFINE_list("seeds", None, "Seeds trained together in every run (experiments.train --seeds: one "
                           "program per level): each combination's workdir gets a seed=S workdir per seed.")
Job = TypeVar("Job")
Result = TypeVar("Result")


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


def check_passed_flags(extra: list[str], swept: set[str]) -> None:
  """Raises ValueError naming the first flag after `--` that the sweep sets itself: --task, --workdir, or one
  in swept (the --grid's names, and --seed(s) with --seeds). Passed on, it would silently replace the sweep's
  value in every run."""
  for arg in extra:
    name = arg.lstrip("-").partition("=")[0]
    if arg.startswith("-") and name in {"task", "workdir"} | swept:
      raise ValueError(f"{arg} after --: the sweep sets --{name} itself (by --task, --workdir, --grid or --seeds): "
                       "give it there")


def run_name(combo: dict[str, str]) -> str:
  """{'num_demos': '64', 'tau_in_termination': '1,0,1'} → 'num_demos=64,tau_in_termination=1:0:1'."""
  return ",".join(f"{k}={v.replace(',', ':')}" for k, v in combo.items()) or "default"


def pending(combos: list[dict[str, str]], workdir: str, seeds: list[str] | None) -> list[tuple[str, dict]]:
  """(workdir, combination) of the combinations not done: without results.json in their workdir (with seeds,
  in each seed=S workdir there)."""
  done = [os.path.join(f"seed={s}", "results.json") for s in seeds] if seeds else ["results.json"]
  runs = [(os.path.join(workdir, run_name(c)), c) for c in combos]
  return [(w, c) for w, c in runs if not all(os.path.isfile(os.path.join(w, d)) for d in done)]


def device_environment(gpu: str | None) -> dict[str, str]:
  """The environment of a run on GPU `gpu` alone, memory allocated as needed; this process's for None."""
  if gpu is None:
    return dict(os.environ)
  return {**os.environ, "CUDA_VISIBLE_DEVICES": gpu, "XLA_PYTHON_CLIENT_PREALLOCATE": "false"}


def run_on_devices(jobs: list[Job], run: Callable[[Job, str | None], Result], devices: list[str | None],
                   parallel: int) -> Iterator[Result]:
  """run(job, device) for every job, at most `parallel` at a time on each device; the results in job order."""
  free = queue.Queue()
  for device in devices * parallel:
    free.put(device)

  def one(job: Job) -> Result:
    device = free.get()  # never empty: as many threads as slots, and each returns its slot
    try:
      return run(job, device)
    finally:
      free.put(device)

  with concurrent.futures.ThreadPoolExecutor(len(devices) * parallel) as pool:
    yield from pool.map(one, jobs)


def _end_with_the_sweep() -> None:
  """In a run's process before it starts (Linux): SIGTERM when the sweep's thread that started it ends, so
  that a sweep killed (even by SIGKILL) leaves no run behind holding its workdir; the run keeps its last
  checkpoint, and the sweep's rerun resumes it."""
  if sys.platform == "linux":
    ctypes.CDLL(None, use_errno=True).prctl(_PR_SET_PDEATHSIG, signal.SIGTERM)


_PR_SET_PDEATHSIG = 1


def _run(task: str, workdir: str, combo: dict[str, str], extra: list[str],
         gpu: str | None) -> tuple[str, int, str | None]:
  """(workdir, exit status, refusal): a run refused before any work (exit status 2) leaves no workdir behind
  and gives its one-line refusal."""
  fresh = not os.path.exists(workdir)
  os.makedirs(workdir, exist_ok=True)
  log = os.path.join(workdir, "stdout.log")
  command = [sys.executable, "-m", "experiments.train", f"--task={task}", f"--workdir={workdir}",
             *(f"--{k}={v}" for k, v in combo.items()), *extra]
  with open(log, "a") as out:
    code = subprocess.run(command, stdout=out, stderr=subprocess.STDOUT, env=device_environment(gpu),
                          preexec_fn=_end_with_the_sweep).returncode
  if code == 2 and fresh and os.listdir(workdir) == ["stdout.log"]:
    with open(log) as f:
      refusal = (f.read().strip().splitlines() or [""])[-1]
    shutil.rmtree(workdir)
    return workdir, code, refusal
  return workdir, code, None


def main(argv):
  extra = argv[1:]
  cli.exit_on_interrupt("every finished run is kept, and a run cut short keeps its checkpoint; rerun the same "
                        "command to go on")
  try:
    combos = parse_grid(_GRID.value)
    check_passed_flags(extra, {name for combo in combos for name in combo} | (
        {"seeds", "seed"} if _SEEDS.value is not None else set()))
  except ValueError as e:
    cli.fail(str(e))
  if not _WORKDIR.value:
    cli.fail("--workdir: must name a directory; got ''")
  if os.path.exists(_WORKDIR.value) and not os.path.isdir(_WORKDIR.value):
    cli.fail(f"--workdir={_WORKDIR.value} is a file, not a directory")
  fresh = not os.path.exists(_WORKDIR.value)
  seeds = _SEEDS.value
  if seeds is not None:
    if any("seed" in c for c in combos):
      cli.fail("--seeds and a --grid of seed: give one of them")
    try:
      seeds = [str(s) for s in cli.seed_list(seeds)]  # as the runs name their seed=S workdirs
    except ValueError as e:
      cli.fail(str(e))
    extra = [f"--seeds={','.join(seeds)}", *extra]
  gpus = _GPUS.value or [None]
  if _GPUS.value is not None and not (_GPUS.value and all(_GPUS.value) and len(set(_GPUS.value)) == len(_GPUS.value)):
    cli.fail(f"--gpus={','.join(_GPUS.value)}: GPU ids must be distinct and non-empty")
  try:
    tasks.get(_TASK.value)
  except ValueError as e:
    cli.fail(f"--task: {e}")
  cli.writable_folder("workdir", _WORKDIR.value)
  todo = pending(combos, _WORKDIR.value, seeds)
  print(f"{len(combos)} runs, {len(combos) - len(todo)} already done, {len(todo)} to run", flush=True)
  failed, refusals, start = [], [], time.time()
  for ended, (workdir, code, refusal) in enumerate(run_on_devices(
      todo, lambda wc, gpu: _run(_TASK.value, wc[0], wc[1], extra, gpu), gpus, _PARALLEL.value), 1):
    elapsed = time.time() - start
    left = elapsed / ended * (len(todo) - ended)
    print(f"[{ended}/{len(todo)}, {elapsed / 60:.0f} min, about {left / 60:.0f} min left] "
          f"{'done' if code == 0 else f'FAILED (exit {code})'}: {workdir}" + (f": {refusal}" if refusal else ""),
          flush=True)
    if code:
      failed.append(f"{workdir} (refused, nothing written)" if refusal else workdir)
      refusals += [refusal] if refusal else []
  if failed and len(refusals) == len(failed) == len(todo):  # every run refused its flags: a bad grid
    if fresh and os.path.isdir(_WORKDIR.value) and not os.listdir(_WORKDIR.value):
      os.rmdir(_WORKDIR.value)
    cli.fail(f"every run was refused; the first: {refusals[0].removeprefix('error: ')}")
  if failed:
    print(f"{len(failed)} runs failed; see stdout.log in: {', '.join(failed)}", file=sys.stderr)
    sys.exit(1)


if __name__ == "__main__":
  flags.mark_flags_as_required(["task", "workdir"])
  app.run(main, flags_parser=cli.parse_flags)
