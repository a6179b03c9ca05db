"""A run's report: one self-contained page (workdir/report.html; no scripts, nothing fetched) with the run's
settings and results, its learning curves per level, the call graph its procedures were allowed, and three
of its training demonstrations decoded and drawn as `experiments.show` draws them. The training commands
write it at the end of every run; `experiments.report` writes it again."""
from __future__ import annotations

import html
import json
import os

import jax
import numpy as np

from experiments.common import pictures, run_view
from php_jax.data import files, json_lines
from php_jax.demos import Demonstration
from php_jax.model import PHPHierarchy
from php_jax.training.run import METRICS_FILE, REPORT_FILE, RESULTS_FILE

NUM_DRAWN = 3


def write(workdir: str, demos: Demonstration | None = None, numbers: list[int] | None = None) -> str:
  """Writes workdir/report.html (atomically) and returns its path. demos: the run's training demonstrations
  (default: rebuilt as `experiments.show` does), or with numbers, those of the file results.json names that
  `drawn_demonstrations` draws from it, numbers their places there. Raises ValueError naming what cannot be
  read."""
  results = run_view.read_results(workdir)
  if not (isinstance(results.get("test"), dict) and isinstance(results.get("config", {}), dict)):
    raise ValueError(f"{os.path.join(workdir, RESULTS_FILE)}: not a finished run's results (needs its \"test\" "
                     "results and \"config\")")
  model = results.get("model", "php")
  flat = model != "php"
  shown = f"flat {model[5:].upper()}"  # a flat baseline's name as the page shows it: flat LSTM, flat GRU
  run = None if flat else run_view.load(workdir)  # a hierarchy that cannot be read is refused
  title = f"{results.get('task', 'run')}: {workdir}"
  parts = [_summary(results), *_recipe(results), *_split_search(results), "<h2>Learning curves</h2>"]
  curves = pictures.curves_figure(_metrics(workdir), shown if flat else "every level at once")
  parts.append(pictures.svg(curves) if curves else "<p>No training iterations were logged.</p>")
  if flat:
    parts.append(f"<p>No call stack to show: a {shown} has none.</p>")
  else:
    parts += ["<h2>Call graph</h2>", _call_graph(run)]
    source = "its training demonstrations" if numbers is None else results["demos"]
    if demos is None:
      demos, source = run_view.demonstrations(run, None)
    parts.append("<h2>Decoded demonstrations</h2>")
    indices = drawn_demonstrations(demos)
    for index, (drawn, lines) in zip(indices, run_view.decoded(run, demos, indices)):
      number = index if numbers is None else numbers[index]
      caption = (f"demonstration {number} of {source} ({int(demos.length[index])} steps, "
                 f"{'annotated' if demos.strong[index] else 'actions only'})")
      parts += [f"<h3>{html.escape(caption)}</h3>", pictures.svg(run_view.figure(run, drawn, caption)),
                f"<details><summary>call trees</summary><pre>{html.escape(chr(10).join(lines))}</pre></details>"]
  path = os.path.join(workdir, REPORT_FILE)
  files.write_atomically(path, pictures.page(title, parts).encode())
  return path


def write_if_stale(workdir: str, demos: Demonstration | None = None, numbers: list[int] | None = None) -> str | None:
  """write, unless workdir's report.html is newer than its results.json (or this is not the first of several
  processes, which writes the files); returns the path written, or None."""
  if jax.process_index() != 0:
    return None
  path, results = os.path.join(workdir, REPORT_FILE), os.path.join(workdir, RESULTS_FILE)
  if os.path.exists(path) and os.path.getmtime(path) >= os.path.getmtime(results):
    return None
  return write(workdir, demos, numbers)


def drawn_demonstrations(demos: Demonstration) -> list[int]:
  """The (up to) three demonstrations a report draws: actions-only ones where there are any (what the model
  had to segment on its own), of short, middle and long length among them."""
  strong = np.asarray(demos.strong)
  candidates = np.flatnonzero(~strong) if (~strong).any() else np.arange(len(strong))
  by_length = candidates[np.argsort(np.asarray(demos.length)[candidates], kind="stable")]
  picks = np.linspace(0, len(by_length) - 1, NUM_DRAWN).round().astype(int)
  return sorted({int(by_length[p]) for p in picks})


def _metrics(workdir: str) -> list[dict]:
  """metrics.jsonl's rows; ValueError naming the line that is not a row a run logs."""
  path = os.path.join(workdir, METRICS_FILE)
  if not os.path.exists(path):
    return []
  rows = []
  with open(path, "rb") as f:
    for number, line in json_lines.lines(f):
      try:
        row = json_lines.loads(line)
      except ValueError as e:
        raise ValueError(f"{path}:{number}: {e}") from None
      numbers = ("iteration", "loss", "validation", "level")
      if not (isinstance(row, dict) and all(row.get(k) is None or _is_number(row[k]) for k in numbers)):
        raise ValueError(f"{path}:{number}: not a metrics row (its iteration, loss, validation and level must be "
                         "numbers)")
      rows.append(row)
  return rows


def _is_number(x) -> bool:
  return isinstance(x, (int, float)) and not isinstance(x, bool)


def _summary(results: dict) -> str:
  """The settings and results as two tables."""
  keys = ("model", "num_demos", "num_strong", "num_annotated", "seed", "demos", "hierarchy", "wall_seconds")
  config = results.get("config") or {}
  rows = [(k, results[k]) for k in keys if k in results]
  rows += [(f"--{k}", config[k]) for k in ("training", "call_graph", "iterations", "hidden") if k in config]
  settings = "".join(f"<tr><td>{html.escape(k)}</td><td>{html.escape(str(v))}</td></tr>" for k, v in rows)
  test = results.get("test") or {}
  tested = "".join(f"<tr><td>{html.escape(str(k))}</td><td>{_number(v)}</td></tr>" for k, v in test.items())
  return (f"<h2>Settings</h2><table>{settings}</table>"
          f"<h2>Results</h2><table><tr><th>test set</th><th>result</th></tr>{tested}</table>")


def _recipe(results: dict) -> list[str]:
  """How the run chose to train: the reasons, and each candidate tried with its held-out score."""
  recipe = results.get("recipe")
  if not isinstance(recipe, dict):
    return []
  reasons = "".join(f"<li>{html.escape(str(r))}</li>" for r in recipe.get("reasons") or [])
  scores = {s.get("name"): s for s in recipe.get("scores") or []}
  rows = "".join(
      f"<tr><td>{html.escape(str(c.get('name')))}{' (chosen)' if c.get('name') == recipe.get('chosen') else ''}"
      f"</td><td>{html.escape(json.dumps(c.get('settings')))}</td>"
      f"<td>{scores.get(c.get('name'), {}).get('held_out_explained', '–')}</td>"
      f"<td>{scores.get(c.get('name'), {}).get('training_explained', '–')}</td>"
      f"<td>{_number(scores.get(c.get('name'), {}).get('held_out_log_likelihood_per_step'))}</td>"
      f"<td>{_number(scores.get(c.get('name'), {}).get('wall_seconds'))}</td></tr>"
      for c in recipe.get("candidates") or [])
  return [f"<h2>Recipe</h2><ul>{reasons}</ul><table><tr><th>candidate</th><th>settings</th>"
          f"<th>held-out demonstrations explained (of {recipe.get('judged_on', '–')})</th>"
          f"<th>training demonstrations explained</th><th>held-out "
          f"log-likelihood per step</th><th>seconds</th></tr>{rows}</table>"]


def _split_search(results: dict) -> list[str]:
  """A joint run's split-search rounds as a table (none where it made none)."""
  rounds = (results.get("joint") or {}).get("split_search") or []
  rows = "".join(f"<tr><td>{r['round'] + 1}</td><td>{html.escape(str(r['kept']))}</td>"
                 f"<td>{_number(r['log_likelihood_per_step'])}</td><td>{len(r['candidates'])}</td></tr>"
                 for r in rounds)
  return [f"<h2>Split search</h2><table><tr><th>round</th><th>kept</th><th>validation log-likelihood per step</th>"
          f"<th>candidates</th></tr>{rows}</table>"] if rounds else []


def _number(value) -> str:
  return f"{value:.3f}" if isinstance(value, float) else html.escape(str(value))


def _call_graph(run: run_view.RunView) -> str:
  """Per level below the root, which operations each procedure may take (its allowed_ops), as a table."""
  hierarchy: PHPHierarchy = run.hierarchy
  spec = hierarchy.spec
  rows = []
  for level in range(spec.num_levels):
    allowed = hierarchy.levels[level].allowed_ops
    for h in range(spec.num_procs(level)):
      if allowed is None or all(allowed[h]):
        taken = "any"
      elif level < spec.num_levels - 1:
        taken = ", ".join(run.procedure_name(level + 1, c) for c, ok in enumerate(allowed[h]) if ok)
      else:
        taken = _allowed_actions(run, allowed[h], spec.action_sizes)
      rows.append(f"<tr><td>{level}</td><td>{html.escape(run.procedure_name(level, h))}</td>"
                  f"<td>{html.escape(taken)}</td></tr>")
  return ("<table><tr><th>level</th><th>procedure</th><th>may call or take</th></tr>" + "".join(rows)
          + "</table>")


def _allowed_actions(run: run_view.RunView, allowed, sizes) -> str:
  """A lowest-level procedure's allowed values per action factor (named where there is one factor)."""
  parts, offset = [], 0
  for factor, size in enumerate(sizes):
    values = [v for v in range(size) if allowed[offset + v]]
    offset += size
    shown = [run.action_name([v]) for v in values] if len(sizes) == 1 else [str(v) for v in values]
    parts.append(", ".join(shown) if len(sizes) == 1 else f"factor {factor}: {', '.join(shown)}")
  return "; ".join(parts)
