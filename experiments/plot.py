r"""Figures and tables from the results.json files of training runs (e.g. those of experiments.sweep).

  python -m experiments.plot --runs=runs/nc_sweep --out=results

NanoCraft (paper Figure 2): test accuracy against the number of strongly supervised demonstrations, one line
per total number of demonstrations (the flat LSTM, which ignores annotations, as a dashed level in the same
colour; weak-only PHP runs as a dotted one), mean over trials with min–max bars → OUT/nanocraft.png and
OUT/nanocraft.md (which adds the mean decoding agreement with the supervisor at level 1, by exact procedure
ids and up to a renaming of them). Addition (paper Table 2): per model and number of strong traces, the mean
accuracy at each test length and in how many seeds it is 100% → OUT/addition.png and OUT/addition.md.
"""
from __future__ import annotations

import glob
import json
import os
import sys
from collections import defaultdict

import matplotlib
import numpy as np
from absl import app, flags

matplotlib.use("Agg")
from matplotlib import pyplot as plt  # noqa: E402  (after choosing the file-only backend)

from php_jax import checkpoint  # noqa: E402

_RUNS = flags.DEFINE_multi_string("runs", None, "Directories searched (recursively) for results.json.")
_OUT = flags.DEFINE_string("out", "results", "Output directory for the PNG and Markdown files.")


def load_results(directories: list[str]) -> list[dict]:
  """Every results.json below the directories."""
  results = []
  for directory in directories:
    for path in sorted(glob.glob(os.path.join(directory, "**", "results.json"), recursive=True)):
      with open(path) as f:
        results.append(json.load(f))
  return results


def nanocraft_groups(results: list[dict]) -> dict[tuple[str, int, int], list[float]]:
  """(model, num_demos, num_strong) → test accuracies of its trials (num_strong 0 for the flat LSTM, which
  uses actions only)."""
  groups = defaultdict(list)
  for r in results:
    if r["task"] == "nanocraft":
      model = r.get("model", "php")
      strong = r["num_strong"] if model == "php" else 0
      groups[(model, r["num_demos"], strong)].append(r["test"]["accuracy"])
  return dict(sorted(groups.items()))


def nanocraft_agreements(results: list[dict]) -> dict[tuple[str, int, int], list[tuple[float, float]]]:
  """(model, num_demos, num_strong) → per trial (exact, relabelled or None where not measured) decoding
  agreement at level 1, the level whose segmentation decides the root's training data (trials without weak
  demonstrations left out)."""
  groups = defaultdict(list)
  for r in results:
    level1 = r.get("levels", {}).get("1", {})
    if r["task"] == "nanocraft" and level1.get("decoding_agreement") is not None:
      groups[("php", r["num_demos"], r["num_strong"])].append(
          (level1["decoding_agreement"], level1.get("relabelled_agreement")))
  return dict(groups)


def addition_groups(results: list[dict]) -> dict[tuple[str, int], dict[str, list[float]]]:
  """(model, num_strong) → test length → accuracies of its seeds."""
  groups = defaultdict(lambda: defaultdict(list))
  for r in results:
    if r["task"] == "addition":
      for length, acc in r["test"].items():
        groups[(r.get("model", "php"), r["num_strong"])][length].append(acc)
  return {k: dict(v) for k, v in sorted(groups.items())}


def nanocraft_markdown(groups, agreements=None) -> str:
  agreements = agreements or {}
  lines = ["| model | demonstrations | strong | trials | accuracy mean | min | max | "
           "level-1 agreement mean: exact ids, up to renaming |",
           "| --- | --- | --- | --- | --- | --- | --- | --- |"]
  for key, accs in groups.items():
    model, total, strong = key
    agree = agreements.get(key)
    agree_text = "–"
    if agree:  # both means over the trials that measured the relabelled one, when some did
      measured = [(a, r) for a, r in agree if r is not None] or agree
      agree_text = f"{np.mean([a for a, _ in measured]):.3f}, "
      agree_text += f"{np.mean([r for _, r in measured]):.3f}" if measured[0][1] is not None else "–"
      if len(measured) < len(agree):
        agree_text += f" ({len(measured)} of {len(agree)} trials)"
    lines.append(f"| {model} | {total} | {strong} | {len(accs)} | {np.mean(accs):.3f} | {min(accs):.3f} | "
                 f"{max(accs):.3f} | {agree_text} |")
  return "\n".join(lines) + "\n"


def addition_markdown(groups) -> str:
  lengths = sorted({n for by_length in groups.values() for n in by_length}, key=int)
  lines = ["| model | strong | " + " | ".join(f"{n} digits: mean (seeds at 100%)" for n in lengths) + " |",
           "| --- | --- | " + " | ".join("---" for _ in lengths) + " |"]
  for (model, strong), by_length in groups.items():
    cells = []
    for n in lengths:
      accs = by_length.get(n, [])
      cells.append(f"{np.mean(accs):.3f} ({sum(a == 1.0 for a in accs)}/{len(accs)})" if accs else "–")
    lines.append(f"| {model} | {strong} | " + " | ".join(cells) + " |")
  return "\n".join(lines) + "\n"


def nanocraft_figure(groups, path: str) -> None:
  fig, ax = plt.subplots(figsize=(6, 4))
  lines = defaultdict(list)
  for (model, total, strong), accs in groups.items():
    lines[(model, total)].append((strong, np.mean(accs), min(accs), max(accs)))
  totals = sorted({total for _, total in lines})
  color = {total: f"C{i}" for i, total in enumerate(totals)}  # a data-set size keeps its colour throughout
  for (model, total), points in sorted(lines.items()):
    x, mean, low, high = map(np.array, zip(*sorted(points)))
    if model == "php" and np.any(x > 0):
      annotated = x > 0
      ax.errorbar(x[annotated], mean[annotated], yerr=[(mean - low)[annotated], (high - mean)[annotated]],
                  marker="o", capsize=3, color=color[total], label=f"PHP-{total}")
    if model == "php" and x[0] == 0:  # weak only: no place on the log axis, one level across it
      ax.axhline(mean[0], linestyle=":", color=color[total], label=f"PHP-{total}, weak only ({mean[0]:.3f})")
    elif model != "php":  # actions only: one level across the axis
      ax.axhline(mean[0], linestyle="--", color=color[total], alpha=0.6,
                 label=f"flat LSTM-{total} ({mean[0]:.3f})")
  ax.set_xscale("log", base=2)
  ax.set_xlabel("strongly supervised demonstrations")
  ax.set_ylabel("test accuracy")
  ax.set_ylim(0, 1.02)
  ax.legend(loc="upper left", fontsize=8)
  ax.grid(alpha=0.3)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def table_figure(markdown: str, path: str) -> None:
  """A Markdown table drawn as a PNG."""
  rows = [[c.strip() for c in line.strip("|").split("|")] for line in markdown.strip().splitlines()]
  rows = [rows[0]] + rows[2:]  # drop the separator
  fig, ax = plt.subplots(figsize=(2 + 2.2 * len(rows[0]), 0.6 + 0.35 * len(rows)))
  ax.axis("off")
  table = ax.table(cellText=rows[1:], colLabels=rows[0], loc="center")
  table.auto_set_font_size(False)
  table.set_fontsize(8)
  fig.tight_layout()
  fig.savefig(path, dpi=120)
  plt.close(fig)


def main(argv):
  del argv
  results = load_results(_RUNS.value)
  if not results:
    print(f"error: no results.json under {_RUNS.value}", file=sys.stderr)
    sys.exit(2)
  written = []
  nanocraft, addition = nanocraft_groups(results), addition_groups(results)
  outputs = {}
  if nanocraft:
    outputs["nanocraft.md"] = nanocraft_markdown(nanocraft, nanocraft_agreements(results)).encode()
  if addition:
    outputs["addition.md"] = addition_markdown(addition).encode()
  os.makedirs(_OUT.value, exist_ok=True)
  for name, data in outputs.items():
    checkpoint.write_atomically(os.path.join(_OUT.value, name), data)
    written.append(name)
  if nanocraft:
    _draw_atomically(lambda p: nanocraft_figure(nanocraft, p), os.path.join(_OUT.value, "nanocraft.png"))
    written.append("nanocraft.png")
  if addition:
    _draw_atomically(lambda p: table_figure(outputs["addition.md"].decode(), p),
                     os.path.join(_OUT.value, "addition.png"))
    written.append("addition.png")
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
  app.run(main)
