r"""Writes the keypad example's files: a level whose procedures differ only in their first action.

  python examples/keypad/make_files.py   # writes keypad.json, train.jsonl, held_out.jsonl here
  python examples/keypad/make_files.py --out_dir=DIR --num_train=64 --num_annotated=16 --num_held_out=200 --seed=0

A guard serves 2 to 4 requests at a door's keypad, each to unlock or to lock the door with its own code of 2 to
4 digits (keys 0 to 3). The keypad is slow: the guard types each digit by pressing its key, then enter, then
waiting for the busy light to go out, which accepts the digit. With the whole code accepted, the guard presses
open or lock, which clears the display; the next request follows. Elementary actions: 0 to 3 the keys, 4
enter, 5 wait, 6 open, 7 lock. Observation (10 numbers), about the request being served (all 0 once none is
left): the code's next digit (4 numbers, one-hot; 0 once all are accepted), digits accepted / 4, digits left
/ 4, a key pressed but not entered, the busy light, the request is to unlock, requests left / 4. The
recorded stacks follow the hierarchy

  serve (root) -> unlock, lock -> type_0 .. type_3, press_open, press_lock -> elementary actions

serve calls unlock or lock as the request says; each types the code's digits one call at a time, then calls
press_open (unlock) or press_lock (lock), and returns when the display is clear. type_k = key k, enter, wait:
the four type procedures differ only in their first action (and unlock and lock only in their last call);
press_open and press_lock take one action each. Every decision is a function of the observation and the
deciding procedure's counter (`next_operation`), so the stacks are a function of the observations
(`supervisor_step`). train.jsonl has --num_train demonstrations, the first --num_annotated with their stack;
held_out.jsonl --num_held_out more, all with stacks, drawn from other random seeds (for measuring how well
decoding recovers them).
"""
import argparse
import json
import os

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))
NUM_KEYS, MAX_CODE, MAX_REQUESTS = 4, 4, 4
LEVELS = [["serve"], ["unlock", "lock"], [*(f"type_{k}" for k in range(NUM_KEYS)), "press_open", "press_lock"]]
ACTIONS = [*(f"key_{k}" for k in range(NUM_KEYS)), "enter", "wait", "open", "lock"]
ENTER, WAIT, OPEN, LOCK = range(NUM_KEYS, NUM_KEYS + 4)


def next_operation(level: int, procedure: int, tau: int, o) -> int | None:
  """The supervisor's next operation for a procedure of a level that has executed tau operations, seeing
  observation o: the index of the level below's procedure that it calls (at the lowest level, the elementary
  action), or None when it returns."""
  name = LEVELS[level][procedure]
  pending, busy, unlock = (x > 0.5 for x in o[6:9])
  if level == 0:
    callee = ("unlock" if unlock else "lock") if o[9] > 0 else None
  elif level == 1:
    if tau and o[4] < 0.5 / MAX_CODE:
      callee = None  # the display is clear again: the door opened or locked
    elif o[5] > 0:
      callee = f"type_{int(np.argmax(o[:NUM_KEYS]))}"
    else:
      callee = "press_open" if name == "unlock" else "press_lock"
  elif name.startswith("type_"):
    return int(name[-1]) if tau == 0 else ENTER if pending else WAIT if busy else None
  else:  # press_open, press_lock: one action each
    return None if tau else OPEN if name == "press_open" else LOCK
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
  """The supervisor's demonstration on random requests, with its stack."""
  num_requests = int(rng.integers(2, MAX_REQUESTS + 1))
  codes = [rng.integers(NUM_KEYS, size=rng.integers(2, MAX_CODE + 1)).tolist() for _ in range(num_requests)]
  unlocks = (rng.random(num_requests) < 0.5).tolist()
  request, accepted, pending, busy = 0, 0, False, False

  def observe():
    if request == num_requests:
      return [0.0] * 10
    code = codes[request]
    next_digit = [float(accepted < len(code) and code[accepted] == k) for k in range(NUM_KEYS)]
    return next_digit + [accepted / MAX_CODE, (len(code) - accepted) / MAX_CODE, float(pending), float(busy),
                         float(unlocks[request]), (num_requests - request) / MAX_REQUESTS]

  observations, actions, stack, frames = [observe()], [], [], None
  while step := supervisor_step(frames, observations[-1]):
    frames, action = step
    stack.append(frames)
    actions.append(action)
    if action < NUM_KEYS:
      pending = True
    elif action == ENTER:
      pending, busy = False, True
    elif action == WAIT:
      busy, accepted = False, accepted + 1
    else:  # open or lock: the display clears for the next request
      request, accepted = request + 1, 0
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
  with open(os.path.join(args.out_dir, "keypad.json"), "w") as f:
    json.dump({"levels": LEVELS, "action_sizes": [len(ACTIONS)], "action_names": [ACTIONS]}, f)
    f.write("\n")
  write_lines(os.path.join(args.out_dir, "train.jsonl"), [
      demo if i < args.num_annotated else {k: v for k, v in demo.items() if k != "stack"}
      for i, demo in enumerate(train)])
  write_lines(os.path.join(args.out_dir, "held_out.jsonl"), held_out)


if __name__ == "__main__":
  main()
