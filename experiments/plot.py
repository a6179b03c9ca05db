r"""Figures and tables from the results.json files of training runs (e.g. those of experiments.sweep), or a figure
redrawn from a table this command wrote before.

  python -m experiments.plot --runs=runs/sweep --out=results
  python -m experiments.plot --tables=results/nanocraft.md --out=results

Per task: OUT/TASK.md, a table with one row per (model, demonstrations, strongly supervised) and, per test set
(a test length, or "accuracy"), the mean test accuracy over trials with its range and the trials at 100%,
then the mean decoding agreement with the supervisor at level 1 (the level whose segmentation decides the
root's training data), by exact procedure ids and up to a renaming of them; and OUT/TASK.png. With
--against=annotated (the default) the figure has one panel per test set (two to a row): the accuracy against the
number of annotated demonstrations (paper Figure 2; log scale, ticks at the measured numbers), one line per model
and number of demonstrations ("PHP, 64 demonstrations"; runs trained with --training=joint dash-dotted, runs with
a --call_graph other than "all" solid with triangles), the mean over trials with min–max bars, and the flat LSTM
(which ignores annotations) and runs with nothing annotated as levels across the panel, their values in the
legend. With --against=test_size it has one panel: the accuracy against the test problems' size, one line per row
of the table. With --tables the figure is drawn from the table alone (TABLE's name gives the task); the table is
left as it is.
"""
from __future__ import annotations

import glob
import io
import json
import os
import re
from collections import defaultdict
from typing import NamedTuple

import matplotlib
import numpy as np
from absl import app, flags

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402  (after choosing the file-only backend)

from experiments.common import cli  # noqa: E402
from php_jax.data import files

_RUNS = flags.DEFINE_multi_string("runs", None, "Directories searched (recursively) for results.json.")
_TABLES = flags.DEFINE_multi_string("tables", None, "Tables this command wrote (TASK.md) to draw figures from, "
                                    "instead of --runs.")
_OUT = flags.DEFINE_string("out", "results", "Output directory for the PNG and Markdown files.")
_AGAINST = flags.DEFINE_enum("against", "annotated", ["annotated", "test_size"],
                             "The figure's horizontal axis: the number of annotated demonstrations, one panel per "
                             "test set; or the test problems' size, one panel.")

Key = tuple[str, int, int]  # (model, demonstrations, strongly supervised)


class Accuracy(NamedTuple):
  """One test set's accuracy over a row's trials; at_one: how many trials scored 1.0 (None: not recorded)."""
  mean: float
  low: float
  high: float
  at_one: int | None
  trials: int


class Row(NamedTuple):
  """A table row: the number of trials, the accuracy per test set, the level-1 agreement as written."""
  trials: int
  tests: dict[str, Accuracy]
  agreement: str


def load_results(directories: list[str]) -> list[dict]:
  """Every results.json below the directories; raises ValueError naming a file that is not one."""
  results = []
  for directory in directories:
    for path in sorted(glob.glob(os.path.join(directory, "**", "results.json"), recursive=True)):
      try:
        with open(path, encoding="utf-8") as f:
          result = json.load(f)
        _check_result(result)
      except (OSError, ValueError) as e:  # UnicodeDecodeError and JSONDecodeError are ValueErrors
        raise ValueError(f"{path}: not a training run's results ({e})") from None
      results.append(result)
  return results


def _check_result(result) -> None:
  """Raises ValueError unless result has what the tables and figures read."""
  if not (isinstance(result, dict) and isinstance(result.get("task"), str) and isinstance(result.get("test"), dict)):
    raise ValueError('needs "task" and "test"')
  if not all(isinstance(a, (int, float)) and not isinstance(a, bool) for a in result["test"].values()):
    raise ValueError('"test" must map test sets to accuracies')
  if not isinstance(result.get("model", "php"), str) or not isinstance(result.get("num_demos", 0), int):
    raise ValueError('"model" must be a string and "num_demos" an integer')
  if result.get("model", "php") == "php" and not isinstance(result.get("num_strong"), int):
    raise ValueError('a PHP run needs an integer "num_strong"')


def group_runs(results: list[dict]) -> dict[str, dict[Key, list[dict]]]:
  """task → (model, num_demos, num_strong) → its trials' results; model is "php" (level-wise), "php-joint", either
  followed by "-" and the call graph where it is not "all" (e.g. "php-joint-operations"), or "flat_lstm" or
  "flat_gru" (num_strong 0: it uses actions only)."""
  groups = defaultdict(lambda: defaultdict(list))
  for r in results:
    model = r.get("model", "php")
    config = r.get("config", {})
    if model == "php" and config.get("training") == "joint":
      model = "php-joint"
    if not _flat(model) and config.get("call_graph", "all") != "all":
      model += "-" + config["call_graph"]
    groups[r["task"]][(model, r.get("num_demos", 0), r["num_strong"] if not _flat(model) else 0)].append(r)
  return {task: dict(sorted(by_key.items())) for task, by_key in sorted(groups.items())}


def summarise(runs: dict[Key, list[dict]]) -> dict[Key, Row]:
  """Each group of trials as its table row."""
  table = {}
  for key, trials in runs.items():
    tests = {}
    for name in {name for r in trials for name in r["test"]}:
      accs = [r["test"][name] for r in trials if name in r["test"]]
      tests[name] = Accuracy(float(np.mean(accs)), min(accs), max(accs), sum(a == 1.0 for a in accs), len(accs))
    table[key] = Row(len(trials), tests, _agreement_text(trials))
  return table


def test_sets(table: dict[Key, Row]) -> list[str]:
  """The test sets' names, "accuracy" first, then lengths in increasing order."""
  names = {name for row in table.values() for name in row.tests}
  return sorted(names, key=lambda n: (n != "accuracy", int(n) if n.isdigit() else 0, n))


def _agreement_text(trials: list[dict]) -> str:
  """Mean level-1 decoding agreement (exact, renamed) over the trials that measured it."""
  pairs = [(level1["decoding_agreement"], level1.get("relabelled_agreement")) for r in trials
           for level1 in [r.get("levels", {}).get("1", {})] if level1.get("decoding_agreement") is not None]
  if not pairs:
    return "–"
  measured = [(a, b) for a, b in pairs if b is not None] or pairs
  text = f"{np.mean([a for a, _ in measured]):.3f}, "
  text += f"{np.mean([b for _, b in measured]):.3f}" if measured[0][1] is not None else "–"
  return text + (f" ({len(measured)} of {len(pairs)} trials)" if len(measured) < len(pairs) else "")


_COLUMN = ": mean (min–max, trials at 1.0)"
_AGREEMENT = "level-1 agreement: exact, renamed"


def markdown(table: dict[Key, Row]) -> str:
  names = test_sets(table)
  lines = ["| model | demonstrations | strong | trials | " + " | ".join(n + _COLUMN for n in names) +
           f" | {_AGREEMENT} |", "| --- | --- | --- | --- | " + " | ".join("---" for _ in names) + " | --- |"]
  for (model, total, strong), row in table.items():
    cells = [_cell(row.tests[n]) if n in row.tests else "–" for n in names]
    lines.append(f"| {model} | {total} | {strong} | {row.trials} | " + " | ".join(cells) + f" | {row.agreement} |")
  return "\n".join(lines) + "\n"


def _cell(a: Accuracy) -> str:
  counted = "" if a.at_one is None else f", {a.at_one}/{a.trials}"
  return f"{a.mean:.3f} ({a.low:.3f}–{a.high:.3f}{counted})"


_CELL = re.compile(r"(\d+(?:\.\d+)?) \((\d+(?:\.\d+)?)–(\d+(?:\.\d+)?)(?:, (\d+)/(\d+))?\)")


def read_table(path: str) -> dict[Key, Row]:
  """The rows of a table markdown() wrote (a cell's ", k/n" may be absent); raises ValueError naming the line."""
  try:
    with open(path, encoding="utf-8") as f:
      lines = [line.strip() for line in f if line.strip()]
  except (OSError, ValueError) as e:
    raise ValueError(f"{path}: cannot be read ({e})") from None
  header = [c.strip() for c in lines[0].strip("|").split("|")] if lines else []
  if header[:4] != ["model", "demonstrations", "strong", "trials"] or header[-1:] != [_AGREEMENT] or not all(
      c.endswith(_COLUMN) for c in header[4:-1]):
    raise ValueError(f"{path}:1: not a table experiments.plot wrote (its header is "
                     f"'| model | demonstrations | strong | trials | NAME{_COLUMN} | ... | {_AGREEMENT} |')")
  names = [c[:-len(_COLUMN)] for c in header[4:-1]]
  table = {}
  for number, line in enumerate(lines[2:], start=3):
    cells = [c.strip() for c in line.strip("|").split("|")]
    try:
      if len(cells) != len(header):
        raise ValueError(f"{len(cells)} cells, the header has {len(header)}")
      key = (cells[0], int(cells[1]), int(cells[2]))
      tests = {name: _read_cell(cell, int(cells[3])) for name, cell in zip(names, cells[4:-1]) if cell != "–"}
    except ValueError as e:
      raise ValueError(f"{path}:{number}: {e}") from None
    table[key] = Row(int(cells[3]), tests, cells[-1])
  return table


def _read_cell(cell: str, trials: int) -> Accuracy:
  match = _CELL.fullmatch(cell)
  if not match:
    raise ValueError(f"cell {cell!r} is not 'mean (min–max, k/n)'")
  mean, low, high = (float(v) for v in match.groups()[:3])
  if not 0 <= low <= mean <= high <= 1:
    raise ValueError(f"cell {cell!r}: needs 0 ≤ min ≤ mean ≤ max ≤ 1")
  at_one, counted = (None, trials) if match[4] is None else (int(match[4]), int(match[5]))
  return Accuracy(mean, low, high, at_one, counted)


_STYLES = {"php": ("o", "-"), "php-joint": ("s", "-.")}  # (marker, line); with a call graph: triangles, solid
_MODES = {"joint": "every level at once"}
_BARS = "mean over trials; bars: min–max"
_SIZES = {"addition": ("numbers of {} digits", "digits per number"), "bubblesort": ("arrays of {} digits",
                                                                                  "digits per array")}


def _size_words(task: str) -> tuple[str, str]:
  """A test set's title for its size, and the size axis's label, in the task's own unit."""
  return _SIZES.get(task, ("test problems of size {}", "test problem size"))


def _flat(model: str) -> bool:
  """Whether a model name is a flat baseline's (flat_lstm, flat_gru), which takes no annotation."""
  return model.startswith("flat_")


def _label(model: str, total: int) -> str:
  """A line's legend: the model, the number of demonstrations, how it was trained."""
  if _flat(model):
    return f"flat {model[5:].upper()}, {total} demonstrations"
  parts = model.split("-")[1:]
  how = [_MODES.get(p, f"call graph: {p}") for p in parts]
  return ", ".join([f"PHP, {total} demonstrations", *how])


def figure(table: dict[Key, Row], task: str = "") -> bytes:
  """Per test set one panel: test accuracy against the number of annotated demonstrations (log scale, ticks
  at the measured numbers), a line per model and number of demonstrations, the mean over trials with
  min–max bars; the flat LSTM and runs with nothing annotated as levels across the panel. Returns the PNG's
  bytes."""
  names = test_sets(table)
  columns = min(2, len(names))
  rows = -(-len(names) // columns)
  fig, axes = plt.subplots(rows, columns, figsize=(6.4 * columns, 4.2 * rows + 0.6), squeeze=False)
  totals = sorted({total for _, total, _ in table})
  color = {total: f"C{i}" for i, total in enumerate(totals)}  # a data-set size keeps its colour throughout
  measured = sorted({strong for _, _, strong in table if strong > 0})
  for ax, name in zip(axes.flat, names):
    lines = defaultdict(list)
    for (model, total, strong), row in table.items():
      if name in row.tests:
        a = row.tests[name]
        lines[(model, total)].append((strong, a.mean, a.low, a.high))
    for (model, total), points in sorted(lines.items()):
      x, mean, low, high = map(np.array, zip(*sorted(points)))
      php, label = not _flat(model), _label(model, total)
      if php and np.any(x > 0):
        annotated = x > 0
        marker, linestyle = _STYLES.get(model, ("^", "-"))
        ax.errorbar(x[annotated], mean[annotated], yerr=[(mean - low)[annotated], (high - mean)[annotated]],
                    marker=marker, linestyle=linestyle, capsize=3, color=color[total], label=label)
      if php and x[0] == 0:  # nothing annotated: no place on the log axis, one level across it
        ax.axhline(mean[0], linestyle=":", linewidth=2, color=color[total],
                   label=f"{label}, none annotated ({mean[0]:.3f})")
      elif not php:  # actions only: one level across the axis
        ax.axhline(mean[0], linestyle="--", linewidth=2, color=color[total], label=f"{label} ({mean[0]:.3f})")
    _log_axis(ax, measured, "annotated demonstrations (log scale)")
    ax.set_title("fresh test problems" if name == "accuracy" else _size_words(task)[0].format(name), fontsize=10)
  for ax in list(axes.flat)[len(names):]:
    ax.set_visible(False)
  fig.suptitle(f"{task + ': ' if task else ''}test accuracy against the number of annotated demonstrations\n"
               f"({_BARS})", fontsize=11)
  return _png(fig)


def size_figure(table: dict[Key, Row], task: str = "") -> bytes:
  """One panel: test accuracy against the test problems' size (log scale, ticks at the measured sizes), a line
  per table row, the mean over trials with min–max bars. Returns the PNG's bytes."""
  sizes = sorted(int(n) for n in test_sets(table) if n.isdigit())
  fig, ax = plt.subplots(figsize=(7.4, 4.8))
  for i, ((model, total, strong), row) in enumerate(table.items()):
    points = [(s, row.tests[str(s)]) for s in sizes if str(s) in row.tests]
    if not points:
      continue
    x = np.array([s for s, _ in points])
    mean, low, high = (np.array([getattr(a, f) for _, a in points]) for f in ("mean", "low", "high"))
    annotated = "" if _flat(model) else f", {strong} annotated"
    ax.errorbar(x, mean, yerr=[mean - low, high - mean], marker=("o", "s", "^", "D", "v")[i % 5], capsize=3,
                color=f"C{i}", label=f"{_label(model, total)}{annotated} ({row.trials} trials)")
  _log_axis(ax, sizes, f"{_size_words(task)[1]} (log scale)")
  ax.set_title(f"{task + ': ' if task else ''}test accuracy against the test problems' size\n({_BARS})",
               fontsize=11)
  return _png(fig)


def _log_axis(ax, ticks: list[int], label: str) -> None:
  ax.set_xscale("log", base=2)
  if ticks:
    ax.set_xticks(ticks, [str(t) for t in ticks])
    ax.minorticks_off()
  ax.set_xlabel(label)
  ax.set_ylabel("test accuracy")
  ax.set_ylim(-0.03, 1.03)  # a level at 0 stays visible
  ax.legend(loc="upper center", bbox_to_anchor=(0.5, -0.16), ncol=2, fontsize=8, frameon=False)
  ax.grid(alpha=0.3)


def _png(fig) -> bytes:
  """The figure as a PNG file's bytes; the figure is closed."""
  fig.tight_layout()
  buffer = io.BytesIO()
  fig.savefig(buffer, format="png", dpi=110, bbox_inches="tight")
  plt.close(fig)
  return buffer.getvalue()


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  if bool(_RUNS.value) == bool(_TABLES.value):
    cli.fail("give either --runs (directories of runs) or --tables (tables this command wrote)")
  if os.path.exists(_OUT.value) and not os.path.isdir(_OUT.value):
    cli.fail(f"--out={_OUT.value} is a file, not a directory")
  try:
    if _TABLES.value:
      tables = {os.path.splitext(os.path.basename(p))[0]: read_table(p) for p in _TABLES.value}
    else:
      results = load_results(_RUNS.value)
      if not results:
        cli.fail(f"no results.json under {_RUNS.value}")
      tables = {task: summarise(runs) for task, runs in group_runs(results).items()}
    if _AGAINST.value == "test_size" and not all(any(n.isdigit() for n in test_sets(t)) for t in tables.values()):
      raise ValueError("--against=test_size needs test sets named by their size")
  except ValueError as e:
    cli.fail(str(e))
  cli.writable_folder("out", _OUT.value)
  draw = size_figure if _AGAINST.value == "test_size" else figure
  written = []
  with cli.output_errors("out", _OUT.value):
    for task, table in tables.items():
      name = task.replace(":", "_").replace("/", "_")
      if not _TABLES.value:
        files.write_atomically(os.path.join(_OUT.value, f"{name}.md"), markdown(table).encode())
        written.append(f"{name}.md")
      files.write_atomically(os.path.join(_OUT.value, f"{name}.png"), draw(table, task))
      written.append(f"{name}.png")
  source = f"{len(tables)} tables" if _TABLES.value else f"{len(results)} runs"
  print(f"{source} -> {', '.join(os.path.join(_OUT.value, w) for w in written)}")


if __name__ == "__main__":
  app.run(main, flags_parser=cli.parse_flags)
