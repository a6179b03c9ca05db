"""What a person at a terminal sees while a command works: for training, a live display (rich) of each phase
(level k of n, lowest first, or every level at once), its iterations done of total, the last loss and best
validation, elapsed time and time left, then a table of the test results and where the model is (away from
a terminal the logged rows as JSON lines instead, `php_jax.training.run.print_row`); for commands that go through
episodes (`act`, `record`), a bar of episodes done of total with the time left (nothing away from a
terminal, where their closing lines say it all)."""
from __future__ import annotations

import contextlib
import sys
from typing import Callable, Iterator

from rich.console import Console
from rich.markup import escape
from rich.progress import (BarColumn, MofNCompleteColumn, Progress, ProgressColumn, Task, TextColumn,
                           TimeElapsedColumn, TimeRemainingColumn)
from rich.table import Table
from rich.text import Text

from php_jax.training import run, selection
from php_jax.training.config import TrainConfig


class TimeLeftColumn(ProgressColumn):
  """"H:MM:SS left" for a task whose total is known and not yet reached; nothing otherwise (elapsed time is
  its own column)."""

  def __init__(self):
    super().__init__()
    self.remaining = TimeRemainingColumn()

  def render(self, task: Task) -> Text:
    if task.total is None or task.finished:
      return Text("")
    left = self.remaining.render(task)
    left.append(" left")
    return left


@contextlib.contextmanager
def counting(total: int, what: str) -> Iterator[Callable[[], None]]:
  """A callback to call once per item done (of total, e.g. episodes), drawn as a bar at a terminal."""
  if not sys.stdout.isatty():
    yield lambda: None
    return
  with Progress(TextColumn(what), BarColumn(), MofNCompleteColumn(), TimeElapsedColumn(), TimeLeftColumn(),
                transient=True) as bar:
    task = bar.add_task(what, total=total)
    yield lambda: bar.advance(task)


@contextlib.contextmanager
def shown(config: TrainConfig, num_levels: int | None, workdir: str) -> Iterator[Callable[[dict], None]]:
  """The echo a training command gives `php_jax.training.run`: a TrainingProgress on a terminal (ended when the block
  ends, however it ends), else JSON lines."""
  if not sys.stdout.isatty():
    yield run.print_row
    return
  progress = TrainingProgress(config, num_levels, workdir)
  try:
    yield progress
  finally:
    progress.close()


class TrainingProgress:
  """echo for `php_jax.training.run`: fed each logged row (and last the test results), it draws the run's progress.

  num_levels: the hierarchy's levels (None for a flat baseline); with several seeds trained together, the
  first seed's rows stand for all."""

  def __init__(self, config: TrainConfig, num_levels: int | None, workdir: str, console: Console | None = None):
    self.config, self.num_levels, self.workdir = config, num_levels, workdir
    self.console = console or Console()
    self.progress = Progress(TextColumn("{task.description}"), BarColumn(), MofNCompleteColumn(),
                             TextColumn("{task.fields[status]}"), TimeElapsedColumn(), TimeLeftColumn(),
                             console=self.console)
    self.tasks, self.seed, self.candidate, self.warned = {}, None, None, set()
    self.progress.start()
    self.starting = self.progress.add_task("building the data and compiling", total=None, status="")

  def __call__(self, row: dict) -> None:
    candidate = row.get("candidate")
    if "chosen" in row or (candidate is not None and "test" in row):
      self._judged(row)
      return
    if "test" in row:
      self._finish(row)
      return
    if candidate is not None and (row.get("phase") == "testing" or "warning" in row and row["warning"] in self.warned):
      return  # a candidate's judging; a warning another candidate gave
    if "warning" in row:
      self.warned.add(row["warning"])
    self.candidate = candidate
    if row.get("phase") == "testing":
      self.progress.add_task("testing", total=None, status="")
      return
    if "warning" in row:  # every seed's
      seed = f"seed {row['seed']}: " if "seed" in row else ""
      self.console.print(f"[yellow]warning:[/] {seed}{escape(row['warning'])}", highlight=False)
      return
    if self.seed is None and "seed" in row:
      self.seed = row["seed"]
    if row.get("seed", self.seed) != self.seed:
      return
    if row.get("resumed"):
      at = "" if row["iteration"] is None else f", iteration {row['iteration']}"
      self.console.print(f"resumed from the checkpoint: level {row['level']}{at}")
    elif "capacity" in row:
      self._phase(row.get("level", "joint"))
      if row.get("unexplained"):
        name = f"{self.candidate}: " if self.candidate else ""
        self.console.print(
            f"[yellow]warning:[/] {name}{row['unexplained']} training demonstrations fit no call stack within "
            f"the counter capacities {row['capacity']} (root first) and the call graph: training leaves them out, "
            "and the model will not act as they do. Allow more (--min_capacity, --call_graph=all), or annotate a "
            "demonstration that shows what they do", highlight=False)
    elif "split_rounds" in row:
      self.tasks[(self.candidate, "split")] = self.progress.add_task("split search", total=row["split_rounds"],
                                                                     status="round 1 training its candidates")
    elif "split_search" in row:
      entry, split = row["split_search"], (self.candidate, "split")
      if split not in self.tasks:  # resumed in the search: its number of rounds was logged before
        self.tasks[split] = self.progress.add_task("split search", total=None, status="")
      score = entry["log_likelihood_per_step"]
      judged = ("no stack fits a validation demonstration" if score is None
                else f"log-likelihood per step {score:.4g}")
      self.progress.update(self.tasks[split], completed=entry["round"] + 1, status=f"kept: {entry['kept']} ({judged})")
    elif "iteration" in row:
      phase = row.get("level", "joint" if self.num_levels else "flat")
      task = self.tasks.get((self.candidate, phase)) or self._phase(phase)
      validation = f"  best validation {row['validation']:.3f}" if "validation" in row else ""
      self.progress.update(task, completed=row["iteration"], status=f"loss {row['loss']:.4g}{validation}")

  def _phase(self, phase) -> int:
    """The display's line for a phase: a level (an int), "joint" or "flat"."""
    self.progress.update(self.starting, visible=False)
    key = (self.candidate, phase)
    if key in self.tasks:
      return self.tasks[key]
    if phase == "joint":
      description, total = "every level at once", self.config.iterations
    elif phase == "flat":
      description, total = "flat baseline", self.config.iterations
    else:
      warmup = self.config.strong_warmup if phase > 0 else 0
      done = self.num_levels - phase
      description, total = f"level {phase} ({done} of {self.num_levels})", warmup + self.config.iterations
    if self.candidate is not None:
      description = f"{self.candidate}: {description}"
    self.tasks[key] = self.progress.add_task(description, total=total, status="compiling")
    return self.tasks[key]

  def _judged(self, row: dict) -> None:
    """A candidate's held-out score, or which candidate was kept."""
    scores = row.get("test", row)  # a candidate's test results are its score
    score = scores.get(selection.SCORE)
    training = scores.get(selection.TRAINING_EXPLAINED)
    judged = (f"{scores.get(selection.EXPLAINED)} held-out"
              + ("" if training is None else f" and {training} training") + " demonstrations explained, "
              "log-likelihood per step " + ("–" if score is None else f"{score:.4g}"))
    if "chosen" in row:
      self.console.print(f"kept candidate {row['chosen']} ({judged})")
    else:
      self.console.print(f"candidate {row['candidate']}: {judged}")

  def _finish(self, row: dict) -> None:
    self.progress.stop()
    self.progress.update(self.starting, visible=False)
    seed = f"seed {row['seed']}: " if "seed" in row else ""
    workdir = f"{self.workdir}/seed={row['seed']}" if "seed" in row else self.workdir
    table = Table(title=f"{seed}test results")
    table.add_column("test set")
    table.add_column("result", justify="right")
    for name, value in row["test"].items():
      table.add_row(name, f"{value:.3f}" if isinstance(value, float) else "–" if value is None else str(value))
    self.console.print(table)
    if row.get("finished_before"):
      self.console.print(f"this run had already finished in {workdir} ({row['wall_seconds']:.0f} s); "
                         "--overwrite trains it again")
    else:
      self.console.print(f"{row['wall_seconds']:.0f} s in all; the model, results.json and metrics.jsonl are in "
                         f"{workdir}")

  def close(self) -> None:
    """Ends the live display (if the run ended before its results)."""
    self.progress.stop()


def report_written(path: str) -> None:
  """Says where a run's report was written: a line at a terminal, else a JSON line {"report": path}."""
  if sys.stdout.isatty():
    Console().print(f"report: {path}")
  else:
    run.print_row({"report": path})
