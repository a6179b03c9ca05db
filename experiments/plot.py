r"""Figures and tables from the results.json files of training runs (e.g. those of experiments.sweep).

  python -m experiments.plot --runs=runs/sweep --out=results

Per task: OUT/TASK.md, a table with one row per (model, demonstrations, strongly supervised) and, per test set
(a test length, or "accuracy"), the mean test accuracy over trials with its range and the trials at 100%,
then the mean decoding agreement with the supervisor at level 1 (the level whose segmentation decides the
root's training data), by exact procedure ids and up to a renaming of them; and OUT/TASK.png, one panel per
test set (two to a row): the accuracy against the number of annotated demonstrations (paper Figure 2; log
scale, ticks at the measured numbers), one line per model and number of demonstrations ("PHP, 64
demonstrations"; runs trained with --training=joint dash-dotted, runs with a --call_graph other than "all"
solid with triangles), the mean over trials with min–max bars, and the flat LSTM (which ignores annotations)
and runs with nothing annotated as levels across the panel, their values in the legend.
"""
from __future__ import annotations

import glob
import json
import os
from collections import defaultdict

import matplotlib
import numpy as np
from absl import app, flags

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402  (after choosing the file-only backend)

from experiments import cli  # noqa: E402
from php_jax import checkpoint  # noqa: E402

_RUNS = flags.DEFINE_multi_string("runs", None, "Directories searched (recursively) for results.json.")
_OUT = flags.DEFINE_string("out", "results", "Output directory for the PNG and Markdown files.")

Key = tuple[str, int, int]  # (model, demonstrations, strongly supervised)


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
  followed by "-" and the call graph where it is not "all" (e.g. "php-joint-operations"), or "flat_lstm"
  (num_strong 0: it uses actions only)."""
  groups = defaultdict(lambda: defaultdict(list))
  for r in results:
    model = r.get("model", "php")
    config = r.get("config", {})
    if model == "php" and config.get("training") == "joint":
      model = "php-joint"
    if model != "flat_lstm" and config.get("call_graph", "all") != "all":
      model += "-" + config["call_graph"]
    groups[r["task"]][(model, r.get("num_demos", 0), r["num_strong"] if model != "flat_lstm" else 0)].append(r)
  return {task: dict(sorted(by_key.items())) for task, by_key in sorted(groups.items())}


def test_sets(runs: dict[Key, list[dict]]) -> list[str]:
  """The test sets' names, "accuracy" first, then lengths in increasing order."""
  names = {name for trials in runs.values() for r in trials for name in r["test"]}
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


def markdown(runs: dict[Key, list[dict]]) -> str:
  names = test_sets(runs)
  lines = ["| model | demonstrations | strong | trials | " + " | ".join(
      f"{n}: mean (min–max, trials at 1.0)" for n in names) + " | level-1 agreement: exact, renamed |",
           "| --- | --- | --- | --- | " + " | ".join("---" for _ in names) + " | --- |"]
  for (model, total, strong), trials in runs.items():
    cells = []
    for name in names:
      accs = [r["test"][name] for r in trials if name in r["test"]]
      cells.append(f"{np.mean(accs):.3f} ({min(accs):.3f}–{max(accs):.3f}, {sum(a == 1.0 for a in accs)}/"
                   f"{len(accs)})" if accs else "–")
    lines.append(f"| {model} | {total} | {strong} | {len(trials)} | " + " | ".join(cells) +
                 f" | {_agreement_text(trials)} |")
  return "\n".join(lines) + "\n"


_STYLES = {"php": ("o", "-"), "php-joint": ("s", "-.")}  # (marker, line); with a call graph: triangles, solid
_MODES = {"joint": "every level at once"}


def _label(model: str, total: int) -> str:
  """A line's legend: the model, the number of demonstrations, how it was trained."""
  if model == "flat_lstm":
    return f"flat LSTM, {total} demonstrations"
  parts = model.split("-")[1:]
  how = [_MODES.get(p, f"call graph: {p}") for p in parts]
  return ", ".join([f"PHP, {total} demonstrations", *how])


def figure(runs: dict[Key, list[dict]], path: str, task: str = "") -> None:
  """Per test set one panel: test accuracy against the number of annotated demonstrations (log scale, ticks
  at the measured numbers), a line per model and number of demonstrations, the mean over trials with
  min–max bars; the flat LSTM and runs with nothing annotated as levels across the panel."""
  names = test_sets(runs)
  columns = min(2, len(names))
  rows = -(-len(names) // columns)
  fig, axes = plt.subplots(rows, columns, figsize=(6.4 * columns, 4.2 * rows + 0.6), squeeze=False)
  totals = sorted({total for _, total, _ in runs})
  color = {total: f"C{i}" for i, total in enumerate(totals)}  # a data-set size keeps its colour throughout
  measured = sorted({strong for _, _, strong in runs if strong > 0})
  for ax, name in zip(axes.flat, names):
    lines = defaultdict(list)
    for (model, total, strong), trials in runs.items():
      accs = [r["test"][name] for r in trials if name in r["test"]]
      if accs:
        lines[(model, total)].append((strong, np.mean(accs), min(accs), max(accs)))
    for (model, total), points in sorted(lines.items()):
      x, mean, low, high = map(np.array, zip(*sorted(points)))
      php, label = model != "flat_lstm", _label(model, total)
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
    ax.set_xscale("log", base=2)
    if measured:
      ax.set_xticks(measured, [str(m) for m in measured])
      ax.minorticks_off()
    ax.set_xlabel("annotated demonstrations (log scale)")
    ax.set_ylabel("test accuracy")
    ax.set_title("fresh test problems" if name == "accuracy" else f"test problems of size {name}", fontsize=10)
    ax.set_ylim(-0.03, 1.03)  # a level at 0 stays visible
    ax.legend(loc="lower right", fontsize=8)
    ax.grid(alpha=0.3)
  for ax in list(axes.flat)[len(names):]:
    ax.set_visible(False)
  fig.suptitle(f"{task + ': ' if task else ''}test accuracy against the number of annotated demonstrations "
               "(mean over trials; bars: min–max)", fontsize=11)
  fig.tight_layout()
  fig.savefig(path, dpi=110)
  plt.close(fig)


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  if os.path.exists(_OUT.value) and not os.path.isdir(_OUT.value):
    cli.fail(f"--out={_OUT.value} is a file, not a directory")
  try:
    results = load_results(_RUNS.value)
  except ValueError as e:
    cli.fail(str(e))
  if not results:
    cli.fail(f"no results.json under {_RUNS.value}")
  os.makedirs(_OUT.value, exist_ok=True)
  written = []
  for task, runs in group_runs(results).items():
    name = task.replace(":", "_").replace("/", "_")
    checkpoint.write_atomically(os.path.join(_OUT.value, f"{name}.md"), markdown(runs).encode())
    _draw_atomically(lambda p, runs=runs, task=task: figure(runs, p, task), os.path.join(_OUT.value, f"{name}.png"))
    written += [f"{name}.md", f"{name}.png"]
  print(f"{len(results)} runs -> {', '.join(os.path.join(_OUT.value, w) for w in written)}")


def _draw_atomically(draw, path: str) -> None:
  temporary = path + ".tmp.png"
  try:
    draw(temporary)
    os.replace(temporary, path)
  except BaseException:
    if os.path.exists(temporary):
      os.remove(temporary)
    raise


if __name__ == "__main__":
  flags.mark_flags_as_required(["runs"])
  app.run(main, flags_parser=cli.parse_flags)
