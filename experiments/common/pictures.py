"""Pictures of what a run learned, as matplotlib figures: a demonstration's call stack as a timeline (one band
per level, the supervisor's beside the decoded one, the elementary actions below), each level's posterior
as a heat map, and learning curves; written as PNG or SVG, or inlined in a self-contained HTML page.
matplotlib is imported when a picture is drawn, not with this module: the commands that import it start half
a second sooner (a refusal, a run without a report)."""
from __future__ import annotations

import html
import io
from typing import TYPE_CHECKING, Callable, Sequence

import numpy as np

from php_jax.data.call_tree import Call, level_calls

if TYPE_CHECKING:
  from matplotlib.figure import Figure

_UNKNOWN_COLOUR = "#d0d0d0"
_MAX_ACTION_LABELS = 80  # longer demonstrations name their actions in the text trace only


def stack_figure(title: str, decoded: Call, procedure_name: Callable[[int, int], str],
                 action_names: Sequence[str], supervisor: Call | None = None,
                 marginals: Sequence[np.ndarray] | None = None) -> Figure:
  """A demonstration's call stack: per level, root first, a band of its calls (coloured by procedure,
  named where the name fits), the supervisor's band under the decoded one where given; the elementary
  actions under the lowest level (up to 80 steps); then, per level below the root, the posterior
  P(procedure at step t) as a heat map (marginals: per level [T, K_i]) with the decoded procedure marked.

  decoded, supervisor: `call_tree.calls` of the stacks; action_names: the action at each step."""
  steps = decoded.end
  bands = []
  for level, calls in enumerate(level_calls(decoded)):
    bands.append((f"level {level}" + (" decoded" if supervisor else ""), calls))
    if supervisor is not None:
      supervised = level_calls(supervisor)
      bands.append((f"level {level} supervisor", supervised[level] if level < len(supervised) else []))
  heat_levels = list(range(1, len(marginals))) if marginals is not None else []
  width = float(np.clip(4 + 0.12 * steps, 8, 22))
  heights = [0.45 * len(bands) + (0.6 if steps <= _MAX_ACTION_LABELS else 0.2)]
  heights += [0.3 * marginals[k].shape[1] + 0.5 for k in heat_levels]
  from matplotlib.figure import Figure
  fig = Figure(figsize=(width, sum(heights) + 0.9), layout="constrained")
  axes = fig.subplots(len(heights), 1, sharex=True, height_ratios=heights, squeeze=False)[:, 0]
  fig.suptitle(title, fontsize=11)
  _draw_bands(axes[0], bands, steps, width, procedure_name, action_names)
  for ax, level in zip(axes[1:], heat_levels):
    _draw_heat_map(fig, ax, level, marginals[level][:steps], decoded, procedure_name)
  axes[-1].set_xlabel("step")
  return fig


def _draw_bands(ax, bands, steps: int, width_inches: float, procedure_name, action_names) -> None:
  import matplotlib
  from matplotlib.patches import Rectangle
  colours = matplotlib.colormaps["tab10"]
  inches_per_step = width_inches * 0.8 / max(steps, 1)
  for row, (_, calls) in enumerate(bands):
    for call in calls:
      colour = colours(call.procedure % 10) if call.procedure >= 0 else _UNKNOWN_COLOUR
      ax.add_patch(Rectangle((call.start, row + 0.08), call.end - call.start, 0.84, facecolor=colour,
                             edgecolor="white", linewidth=1.2))
      name = procedure_name(call.level, call.procedure)
      if len(name) * 0.075 < (call.end - call.start) * inches_per_step:
        ax.text((call.start + call.end) / 2, row + 0.5, name, ha="center", va="center", fontsize=8)
  if steps <= _MAX_ACTION_LABELS:
    for t, name in enumerate(action_names[:steps]):
      ax.text(t + 0.5, len(bands) + 0.1, name, ha="center", va="top", rotation=90, fontsize=6.5)
  ax.set_ylim(len(bands) + (1.6 if steps <= _MAX_ACTION_LABELS else 0.2), 0)
  ax.set_xlim(0, steps)
  ax.set_yticks([row + 0.5 for row in range(len(bands))], [label for label, _ in bands], fontsize=8)
  ax.tick_params(axis="y", length=0)
  for side in ("top", "right", "left"):
    ax.spines[side].set_visible(False)


def _draw_heat_map(fig, ax, level: int, marginal: np.ndarray, decoded: Call, procedure_name) -> None:
  steps, procedures = marginal.shape
  image = ax.imshow(marginal.T, aspect="auto", cmap="Blues", vmin=0, vmax=1, interpolation="nearest",
                    extent=(0, steps, procedures, 0))
  for call in level_calls(decoded)[level]:
    ax.plot([call.start + 0.1, call.end - 0.1], [call.procedure + 0.5] * 2, color="tab:red", linewidth=1.2)
  ax.set_yticks(np.arange(procedures) + 0.5, [procedure_name(level, h) for h in range(procedures)], fontsize=8)
  ax.set_title(f"level {level}: posterior probability of each procedure (red line: decoded)", fontsize=9,
               loc="left")
  fig.colorbar(image, ax=ax, fraction=0.02, pad=0.01)


def curves_figure(rows: Sequence[dict], whole: str = "every level at once") -> Figure | None:
  """Learning curves from metrics.jsonl rows: per phase (a level, lowest first, or the rows without a level,
  titled whole: a joint run, or the flat LSTM), the training loss against the iteration, and the validation
  score where logged. None if no row has a loss."""
  phases: dict = {}
  for row in rows:
    if "iteration" in row and "loss" in row and "seed" not in row:
      phases.setdefault(row.get("level", "joint"), []).append(row)
  if not phases:
    return None
  order = sorted(phases, key=lambda p: -p if isinstance(p, int) else 0)
  from matplotlib.figure import Figure
  fig = Figure(figsize=(min(4.2 * len(order), 16), 3.2), layout="constrained")
  axes = fig.subplots(1, len(order), squeeze=False)[0]
  for ax, phase in zip(axes, order):
    logged = phases[phase]
    ax.plot([r["iteration"] for r in logged], [r["loss"] for r in logged], color="tab:blue")
    ax.set_title(f"level {phase}" if isinstance(phase, int) else whole, fontsize=10)
    ax.set_xlabel("iteration")
    ax.set_ylabel("training loss (nats per demonstration)", color="tab:blue", fontsize=8)
    validated = [r for r in logged if r.get("validation") is not None]
    if validated:
      twin = ax.twinx()
      twin.plot([r["iteration"] for r in validated], [r["validation"] for r in validated], color="tab:orange",
                marker=".")
      twin.set_ylabel("validation score", color="tab:orange", fontsize=8)
  return fig


def save(fig: Figure, path: str, title: str, text: str = "") -> bytes:
  """The figure's file for path: PNG (.png), SVG (.svg) or an HTML page holding it and text (.html)."""
  if path.endswith(".png"):
    buffer = io.BytesIO()
    fig.savefig(buffer, format="png", dpi=110)
    return buffer.getvalue()
  if path.endswith(".svg"):
    return svg(fig).encode()
  return page(title, [svg(fig), f"<pre>{html.escape(text)}</pre>"]).encode()


def svg(fig: Figure) -> str:
  """The figure as an inline <svg> element (its text as text, in the reader's sans-serif font)."""
  import matplotlib
  buffer = io.StringIO()
  with matplotlib.rc_context({"svg.fonttype": "none"}):
    fig.savefig(buffer, format="svg")
  drawn = buffer.getvalue()
  return drawn[drawn.index("<svg"):]


def page(title: str, parts: Sequence[str]) -> str:
  """A self-contained HTML page (no scripts, nothing fetched) of title and parts (HTML fragments)."""
  body = "\n".join(parts)
  return (f'<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8"><title>{html.escape(title)}</title>'
          f"<style>{_STYLE}</style></head>\n<body><h1>{html.escape(title)}</h1>\n{body}\n</body></html>\n")


_STYLE = ("body{font-family:system-ui,sans-serif;margin:2em;max-width:110em;color:#222}"
          "svg{max-width:100%;height:auto}pre{background:#f6f6f6;padding:1em;overflow-x:auto}"
          "table{border-collapse:collapse}td,th{border:1px solid #ccc;padding:.2em .6em;text-align:right}"
          "th:first-child,td:first-child{text-align:left}")

SUFFIXES = (".png", ".svg", ".html")
