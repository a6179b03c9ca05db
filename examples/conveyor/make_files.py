r"""Writes the conveyor example's files: calls whose length varies with the data, beside calls of one action.

  python examples/conveyor/make_files.py   # writes conveyor.json, train.jsonl, held_out.jsonl here
  python examples/conveyor/make_files.py --out_dir=DIR --num_train=64 --num_annotated=16 --num_held_out=200 --seed=0

A worker at a conveyor belt handles 4 to 6 items that arrive 1 to 6 belt steps apart. For each, it runs the
belt forward until the item is in front of it. An item without a tag is fine: the worker stamps it and the
belt takes it on. A tagged item is faulty: the worker inspects it, which shows the bin it belongs in, and
pushes it off the belt to that side. Elementary actions: 0 forward, 1 inspect, 2 stamp, 3 push_left,
4 push_right. Observation (6 numbers), about the next item not yet handled (all 0 once none is left): its
distance / 6, in front of the worker, tagged (seen from afar), belongs left, belongs right (both 0 until
inspected), items left / 6. The recorded stacks follow the hierarchy

  run_belt (root) -> sort_item, skip_item -> advance, inspect, stamp, push_left, push_right -> elementary actions

run_belt calls sort_item for a tagged item and skip_item for another; sort_item = advance, inspect, then
push_left or push_right as the inspection says; skip_item = advance, stamp. advance runs the belt forward
until the item is in front (1 to 6 actions: its calls vary in length with the data); inspect, stamp and the
pushes take one action each. Every decision is a function of the observation and the deciding procedure's
counter (`next_operation`), so the stacks are a function of the observations (`supervisor_step`). train.jsonl
has --num_train demonstrations, the first --num_annotated with their stack; held_out.jsonl --num_held_out
more, all with stacks, drawn from other random seeds (for measuring how well decoding recovers them).
"""
import argparse
import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
LEVELS = [["run_belt"], ["sort_item", "skip_item"], ["advance", "inspect", "stamp", "push_left", "push_right"]]
ACTIONS = ["forward", "inspect", "stamp", "push_left", "push_right"]
FORWARD, INSPECT = 0, 1
MAX_GAP, MAX_ITEMS = 6, 6


def next_operation(level: int, procedure: int, tau: int, o) -> int | None:
  """The supervisor's next operation for a procedure of a level that has executed tau operations, seeing
  observation o: the index of the level below's procedure that it calls (at the lowest level, the elementary
  action), or None when it returns."""
  name = LEVELS[level][procedure]
  in_front, tagged, left, right = (x > 0.5 for x in o[1:5])
  if level == 0:
    callee = ("sort_item" if tagged else "skip_item") if o[5] > 0 else None
  elif level == 1:
    if tau == 0:
      callee = "advance"  # the item is never in front before it
    elif not in_front:
      callee = None  # stamped or pushed off: the next item is on its way
    elif name == "skip_item":
      callee = "stamp"
    else:
      callee = "push_left" if left else "push_right" if right else "inspect"
  elif name == "advance":
    return None if in_front else FORWARD
  else:  # inspect, stamp, push_left, push_right: one action each
    return None if tau else ACTIONS.index(name)
  return None if callee is None else LEVELS[level + 1].index(callee)


def supervisor_step(stack: list | None, o) -> tuple[list, int] | None:
  """The supervisor's stack and action at a step, from its stack at the step before (None at the first) and
  the observation o now; None once the root returns. The lowest procedure takes its next operation or returns
  (and then its caller does, and so on up); each level below the one that resumed starts a fresh call."""
  frames = [list(frame) for frame in stack] if stack else [[0, -1]]  # first step: the root "resumes" at 0
  while frames:
    procedure, tau = frames[-1]
    operation = next_operation(len(frames) - 1, procedure, tau + 1, o)
    if operation is not None:
      frames[-1][1] = tau + 1
      break
    frames.pop()
  else:
    return None
  while len(frames) < len(LEVELS):
    frames.append([operation, 0])
    operation = next_operation(len(frames) - 1, operation, 0, o)
  return frames, operation


def demonstration(rng: np.random.Generator) -> dict:
  """The supervisor's demonstration on random items, with its stack."""
  num_items = int(rng.integers(4, MAX_ITEMS + 1))
  gaps = rng.integers(1, MAX_GAP + 1, size=num_items).tolist()
  tagged = (rng.random(num_items) < 0.5).tolist()
  goes_left = (rng.random(num_items) < 0.5).tolist()
  item, distance, inspected = 0, gaps[0], False

  def observe():
    if item == num_items:
      return [0.0] * 6
    shown = inspected and tagged[item]
    return [distance / MAX_GAP, float(distance == 0), float(tagged[item]), float(shown and goes_left[item]),
            float(shown and not goes_left[item]), (num_items - item) / MAX_ITEMS]

  observations, actions, stack, frames = [observe()], [], [], None
  while step := supervisor_step(frames, observations[-1]):
    frames, action = step
    stack.append(frames)
    actions.append(action)
    if action == FORWARD:
      distance -= 1
    elif action == INSPECT:
      inspected = True
    else:  # stamped, or pushed off: the next item comes
      item, inspected = item + 1, False
      distance = gaps[item] if item < num_items else 0
    observations.append(observe())
  return {"observations": observations, "actions": actions, "stack": stack}


def write_lines(path: str, demos: list[dict]) -> None:
  """Writes demonstrations as JSON lines."""
  with open(path, "w") as f:
    f.writelines(json.dumps(demo) + "\n" for demo in demos)


def main(argv: list[str] | None = None):
  """Writes the hierarchy, train.jsonl and held_out.jsonl as the flags (argv; None: the command line's) say."""
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--out_dir", default=HERE)
  parser.add_argument("--num_train", type=int, default=64)
  parser.add_argument("--num_annotated", type=int, default=16)
  parser.add_argument("--num_held_out", type=int, default=200)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args(argv)
  if not 0 <= args.num_annotated <= args.num_train:
    parser.error(f"--num_annotated must be in 0..--num_train ({args.num_train}); got {args.num_annotated}")
  if args.num_held_out < 1 or args.seed < 0:
    parser.error("--num_held_out must be at least 1 and --seed at least 0")
  train = [demonstration(np.random.default_rng([args.seed, 0, i])) for i in range(args.num_train)]
  held_out = [demonstration(np.random.default_rng([args.seed, 1, i])) for i in range(args.num_held_out)]
  os.makedirs(args.out_dir, exist_ok=True)
  with open(os.path.join(args.out_dir, "conveyor.json"), "w") as f:
    json.dump({"levels": LEVELS, "action_sizes": [len(ACTIONS)], "action_names": [ACTIONS]}, f)
    f.write("\n")
  write_lines(os.path.join(args.out_dir, "train.jsonl"), [
      demo if i < args.num_annotated else {k: v for k, v in demo.items() if k != "stack"}
      for i, demo in enumerate(train)])
  write_lines(os.path.join(args.out_dir, "held_out.jsonl"), held_out)


if __name__ == "__main__":
  main()
