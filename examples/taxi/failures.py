r"""Where Taxi's failures start: splits each measured run's 1,000 acted episodes by their first state.

  python examples/taxi/failures.py --workdir=runs/taxi_measure

An episode that starts with the taxi on a landmark X while the passenger waits at another landmark P asks
Get for a Navigate where the taxi stands on a landmark; the pair (X, P) is *shown* when some training
episode of the run starts the same way. Every other start is *elsewhere*. One line per run of
examples/taxi/measure.py (read from its row.json and episodes.jsonl): the pairs shown of 12, and the
failures among the episodes of each kind.
"""
from __future__ import annotations

import argparse
import glob
import json
import os

import gymnasium

TEST_SEED, TRAIN_SEED = 100000, 10000   # measure.py's: the acted episodes' first seed, and 10000 · seed


def start_pair(env: gymnasium.Env, seed: int) -> tuple[int, int] | None:
  """(X, P) where the episode reset with `seed` starts with the taxi on landmark X and the passenger at
  landmark P != X; None otherwise."""
  state, _ = env.reset(seed=seed)
  row, col, passenger, _ = env.unwrapped.decode(state)
  landmarks = [tuple(landmark) for landmark in env.unwrapped.locs]
  on = landmarks.index((row, col)) if (row, col) in landmarks else None
  return (on, int(passenger)) if on is not None and on != passenger else None


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdir", required=True, help="a workdir of examples/taxi/measure.py")
  args = parser.parse_args()
  env = gymnasium.make("Taxi-v3")
  runs = sorted(glob.glob(os.path.join(args.workdir, "*", "row.json")))
  tests = None
  for done in runs:
    with open(done) as f:
      row = json.load(f)
    with open(os.path.join(os.path.dirname(done), "episodes.jsonl")) as f:
      success = [json.loads(line)["success"] for line in f]
    tests = tests or [start_pair(env, TEST_SEED + i) for i in range(len(success))]
    shown = {start_pair(env, TRAIN_SEED * row["seed"] + i) for i in range(row["demos"])} - {None}
    counts = {kind: [0, 0] for kind in ("elsewhere", "shown", "not shown")}
    for pair, ok in zip(tests, success):
      kind = "elsewhere" if pair is None else "shown" if pair in shown else "not shown"
      counts[kind][0] += not ok
      counts[kind][1] += 1
    print(f"{os.path.basename(os.path.dirname(done))}: pairs shown {len(shown)}/12; failed: "
          + ", ".join(f"{kind} {failed}/{total}" for kind, (failed, total) in counts.items()))


if __name__ == "__main__":
  main()
