r"""Restarts chosen by held-out likelihood: per seed, of the runs that examples/taxi/measure.py made of one
configuration in several workdirs (the same fit flags but --init_seed), the one whose fitted hierarchy
gives the held-out episodes the highest log-likelihood.

  python examples/taxi/likeliest.py --workdirs=runs/taxi_waiting,runs/taxi_waiting_init11,runs/taxi_waiting_init12 \
      --demos=100 --annotated=3 --choose=suggest

The held-out episodes are each workdir's held.jsonl (the same 200 expert episodes in every workdir, recorded
from seed 500000): a user chooses among restarts with demonstrations of their own, never with the
environment's success. Prints, per seed, each restart's held-out log-likelihood per step and success, and
which is chosen; the last line, the chosen runs' successes.
"""
from __future__ import annotations

import argparse
import json
import os

import measure


def main() -> None:
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--workdirs", required=True, help="comma-separated workdirs of measure.py, one per restart")
  parser.add_argument("--demos", type=int, default=100)
  parser.add_argument("--annotated", type=int, default=3)
  parser.add_argument("--choose", default="first", choices=["first", "suggest"])
  parser.add_argument("--seeds", default="1,2,3,4,5")
  args = parser.parse_args()
  picked = []
  for seed in map(int, args.seeds.split(",")):
    restarts = []
    for workdir in args.workdirs.split(","):
      run = os.path.join(workdir, measure.run_name("php", args.demos, args.annotated, args.choose, seed))
      with open(os.path.join(run, "row.json")) as f:
        success = json.load(f)["success"]
      likelihood = measure.decode(run, os.path.join(workdir, "held.jsonl"))["held_out_log_likelihood"]
      restarts.append((likelihood, success, run))
    best = max(restarts)
    picked.append(best[1])
    print(f"seed {seed}: " + "; ".join(f"{run} {ll:.4f} per step, success {ok:.3f}" for ll, ok, run in restarts)
          + f" -> {best[2]}")
  print("chosen: " + " ".join(f"{ok:.3f}" for ok in picked) + f"; {sum(ok >= 0.99 for ok in picked)}/"
        f"{len(picked)} seeds at 0.99 or more")


if __name__ == "__main__":
  main()
