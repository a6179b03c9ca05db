r"""Where a DoorKey hierarchy's failures end: reads the call stacks of each measured run's failed episodes.

  python examples/doorkey/failures.py --workdir=runs/doorkey8_measure [--sampled]

One line per finished PHP run of examples/taxi/measure.py in the workdir (one whose row.json is written; a run
stopped before its decoding is skipped), from its episodes.jsonl, written by `act` taking the most likely decisions,
or with --sampled its episodes_sampled.jsonl (flat baselines record no stacks and are skipped): the episodes that
failed, how many of them never ran the procedure `pickup` (the key was never picked up), and which level-1 procedure
was running at the last step; then, in the run's decoding of the 200 held-out episodes (decoded.jsonl), how many
calls of `navigate_key` the expert's walks to the key were split into, and how many of those calls last one step
(each call's end is a step where `get_key` may return). Procedures are named by examples/doorkey/doorkey.json, which
the annotated episodes pin the learned ones to.
A workdir holding no PHP run is refused in one line, exit status 2.
"""
from __future__ import annotations

import argparse
import collections
import glob
import json
import os
import sys

import numpy as np

from php_jax.data import call_tree

HIERARCHY = os.path.join(os.path.dirname(__file__), "doorkey.json")


def summarise(episodes: list[dict], level1: list[str], pickup: int) -> str:
  """One line on the failed episodes among `episodes` (act's lines): how many, how many never called the
  level-2 procedure number `pickup`, and the level-1 procedure running at each one's last step."""
  failed = [e for e in episodes if not e["success"]]
  no_key = sum(all(step[2][0] != pickup for step in e["stack"]) for e in failed)
  ends = collections.Counter(level1[e["stack"][-1][1][0]] for e in failed if e["stack"])
  return (f"failed {len(failed)}/{len(episodes)}; key never picked up {no_key}; ends in "
          + ", ".join(f"{name} {ends[name]}" for name in level1))


def calls_of(stacks: list[list], procedure: int) -> list[int]:
  """The lengths of the calls of level-2 `procedure` in decoded stacks ([T][level][h, tau] per episode), the
  calls read as `call_tree.calls` reads them."""
  lengths = []
  for stack in stacks:
    frames = np.asarray(stack)
    level2 = call_tree.level_calls(call_tree.calls(frames[..., 0], frames[..., 1]))[2]
    lengths += [call.end - call.start for call in level2 if call.procedure == procedure]
  return lengths


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", required=True, help="a workdir of examples/taxi/measure.py")
  parser.add_argument("--sampled", action="store_true", help="the episodes acted with act --sample")
  args = parser.parse_args()
  with open(HIERARCHY) as f:
    levels = json.load(f)["levels"]
  level1, pickup, navigate_key = levels[1], levels[2].index("pickup"), levels[2].index("navigate_key")
  acted = "episodes_sampled.jsonl" if args.sampled else "episodes.jsonl"
  runs = []
  for done in sorted(glob.glob(os.path.join(args.workdir, "*", "row.json"))):  # finished runs: decoded.jsonl too
    path = os.path.join(os.path.dirname(done), acted)
    if not os.path.exists(path):
      continue
    with open(path) as f:
      episodes = [json.loads(line) for line in f]
    if episodes and episodes[0]["stack"] is not None:
      runs.append((path, episodes))
  if not runs:
    print(f"--workdir={args.workdir} holds no PHP run of examples/taxi/measure.py with an {acted}", file=sys.stderr)
    sys.exit(2)
  for path, episodes in runs:
    with open(os.path.join(os.path.dirname(path), "decoded.jsonl")) as f:
      walks = calls_of([json.loads(line)["stack"] for line in f], navigate_key)
    print(f"{os.path.basename(os.path.dirname(path))}: {summarise(episodes, level1, pickup)}; held out: "
          f"navigate_key calls {len(walks)}, of one step {walks.count(1)}")


if __name__ == "__main__":
  main()
