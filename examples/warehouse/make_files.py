r"""Writes the warehouse example's files: a domain that php_jax knows nothing about, given only as data.

  python examples/warehouse/make_files.py   # writes warehouse.json, train.jsonl, held_out.jsonl here
  python examples/warehouse/make_files.py --out_dir=DIR --num_train=64 --num_annotated=16

A robot on a line of 8 cells fulfils 1 to 3 orders: for each, it walks right to the order's shelf, picks the
item, walks back left to the dock (cell 0) and drops it. Elementary actions: 0 left, 1 right, 2 pick,
3 drop. Observation (6 numbers): position / 7, the current order's shelf / 7, at the shelf, at the dock,
holding an item, orders left / 3. The recorded stacks follow the hierarchy

  fulfil (root) -> fetch, deliver -> go_left, go_right, pick, drop -> elementary actions

(fetch = go_right then pick; deliver = go_left then drop; fulfil = fetch, deliver per order). train.jsonl
has 40 demonstrations (--num_train), the first 4 (--num_annotated) with their stack; held_out.jsonl 100 more,
all with stacks, for measuring how well decoding recovers them.
"""
import argparse
import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
LEVELS = [["fulfil"], ["fetch", "deliver"], ["go_left", "go_right", "pick", "drop"]]
LEFT, RIGHT, PICK, DROP = range(4)


def demonstration(orders: list[int]) -> dict:
  """The supervisor's demonstration of a list of shelf positions (1..7), with its stack."""
  position, holding, observations, actions, stack = 0, False, [], [], []

  def observe(order_index):
    shelf = orders[order_index] if order_index < len(orders) else 0
    return [position / 7, shelf / 7, float(position == shelf), float(position == 0), float(holding),
            (len(orders) - order_index) / 3]

  root_tau = 0
  for k, shelf in enumerate(orders):
    for mid, (mid_tau_calls) in ((0, ((1, RIGHT, shelf), (2, PICK, None))), (1, ((0, LEFT, 0), (3, DROP, None)))):
      for mid_tau, (low, action, target) in enumerate(mid_tau_calls):
        low_tau = 0
        while True:
          observations.append(observe(k))
          actions.append(action)
          stack.append([[0, root_tau], [mid, mid_tau], [low, low_tau]])
          if action == RIGHT:
            position += 1
          elif action == LEFT:
            position -= 1
          elif action == PICK:
            holding = True
          else:
            holding = False
          low_tau += 1
          if target is None or position == target:
            break
      root_tau += 1
  observations.append(observe(len(orders)))
  return {"observations": observations, "actions": [[a] for a in actions], "stack": stack}


def main():
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out_dir", default=HERE)
  parser.add_argument("--num_train", type=int, default=40)
  parser.add_argument("--num_annotated", type=int, default=4)
  args = parser.parse_args()
  if not 0 <= args.num_annotated <= args.num_train:
    parser.error(f"--num_annotated must be in 0..--num_train ({args.num_train}); got {args.num_annotated}")
  rng = np.random.default_rng(0)
  demos = [demonstration(rng.integers(1, 8, size=rng.integers(1, 4)).tolist()) for _ in range(args.num_train + 100)]
  os.makedirs(args.out_dir, exist_ok=True)
  with open(os.path.join(args.out_dir, "warehouse.json"), "w") as f:
    json.dump({"levels": LEVELS, "action_sizes": [4], "action_names": [["left", "right", "pick", "drop"]]}, f)
    f.write("\n")
  with open(os.path.join(args.out_dir, "train.jsonl"), "w") as f:
    for i, demo in enumerate(demos[:args.num_train]):
      f.write(json.dumps(demo if i < args.num_annotated else {k: v for k, v in demo.items() if k != "stack"}) + "\n")
  with open(os.path.join(args.out_dir, "held_out.jsonl"), "w") as f:
    for demo in demos[args.num_train:]:
      f.write(json.dumps(demo) + "\n")


if __name__ == "__main__":
  main()
