r"""Writes a task's supervisor demonstrations, and its hierarchy, in the file formats `experiments.fit` and
`experiments.decode` read.

  python -m experiments.export_demos --task=nanocraft --num_demos=64 --num_strong=16 --seed=1 \
      --out=train.jsonl --hierarchy_out=nanocraft.json
  python -m experiments.export_demos --task=nanocraft --split=test --num_demos=200 --num_strong=200 --seed=1 \
      --out=held_out.jsonl

--split=training gives exactly the training set `experiments.train` builds for the same --seed, --num_demos
and --num_strong (num_strong of them carry their call stack, chosen at random by the seed); validation and
test draw fresh problems with train's seeds for those sets. An --out ending in .shards is written as a binary
set (a directory of shards, for large data sets; docs/own-demonstrations.md), any other as JSON lines.
"""
from __future__ import annotations

import numpy as np
from absl import app, flags

from experiments.common import cli
from php_jax.data import demo_files
from php_jax.envs import datasets, tasks
from php_jax.training.config import MAX_SEED

_TASK = flags.DEFINE_string("task", None, f"The task: one of {', '.join(tasks.TASKS)}, or module:attribute.")
_SPLIT = flags.DEFINE_enum("split", "training", ["training", "validation", "test"], "Which problems.")
_NUM_DEMOS = flags.DEFINE_integer("num_demos", None, "Demonstrations. Default: the task's training set size.",
                                  upper_bound=datasets.MOST_DEMOS)
_NUM_STRONG = flags.DEFINE_integer("num_strong", 0, "How many carry their call stack.")
_SIZE = flags.DEFINE_integer("size", None, "test: problem size (digits, array length) where the task has sizes; "
                             "default: the training distribution.", upper_bound=1 << 20)
_SEED = flags.DEFINE_integer("seed", 0, "Seed (the training command's --seed for the same data).")
_OUT = flags.DEFINE_string("out", None, "Output demonstration file: JSON lines, or a binary set where it ends in "
                           ".shards.")
_HIERARCHY_OUT = flags.DEFINE_string("hierarchy_out", None, "Also write the task's hierarchy file here, with the "
                                      "counter settings the task states (what its demonstrations cannot show).")


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    task = tasks.get(_TASK.value)
  except ValueError as e:
    cli.fail(f"--task: {e}")
  try:
    cli.check_outputs({"out": _OUT.value, "hierarchy_out": _HIERARCHY_OUT.value}, {}, demo_sets=True)
  except ValueError as e:
    cli.fail(str(e))
  num = task.defaults.num_demos if _NUM_DEMOS.value is None else _NUM_DEMOS.value
  if task.defaults.num_demos_fixed and _SPLIT.value == "training" and num != task.defaults.num_demos:
    cli.fail(f"--num_demos: {task.name}'s training set has {task.defaults.num_demos} demonstrations; got {num}")
  if num < 1 or not 0 <= _NUM_STRONG.value <= num:
    cli.fail(f"--num_strong must be in 0..--num_demos={num} and --num_demos ≥ 1; got {_NUM_STRONG.value} of {num}")
  if _SIZE.value is not None and _SPLIT.value != "test":
    cli.fail("--size is for --split=test")
  if _SIZE.value is not None and not task.defaults.test_lengths:
    cli.fail(f"--size: {task.name}'s problems have no size (its tests draw from the training distribution)")
  if _SIZE.value is not None and _SIZE.value < 1:
    cli.fail(f"--size must be a positive integer; got {_SIZE.value}")
  if not 0 <= _SEED.value <= MAX_SEED:
    cli.fail(f"--seed must be an integer in 0..{MAX_SEED}; got {_SEED.value}")
  seed = _SEED.value + datasets.SEED_OFFSETS[_SPLIT.value]
  try:
    if _SPLIT.value == "training":
      problems = task.training_problems(seed, num)
    elif _SPLIT.value == "validation":
      problems = task.validation_problems(seed, num)
    else:
      problems = task.test_problems(seed, num, _SIZE.value)
    _, budget = task.states_and_budget(problems[:1])  # a size the task cannot pose (a one-digit array) is refused
    if budget > np.iinfo(np.int32).max:
      raise ValueError(f"its episodes may take {budget} steps, beyond 32-bit step counts: choose a smaller size")
  except ValueError as e:
    cli.fail(f"--size={_SIZE.value}: {e}" if _SIZE.value is not None else str(e))
  batch = datasets.problem_demonstrations(task, problems, 0)
  annotated = datasets.strong_mask(len(problems), _NUM_STRONG.value, _SEED.value)
  with cli.output_errors("out", _OUT.value):
    demo_files.write_demonstrations(_OUT.value, batch, annotated)
  if _HIERARCHY_OUT.value:
    with cli.output_errors("hierarchy_out", _HIERARCHY_OUT.value):
      demo_files.write_hierarchy(_HIERARCHY_OUT.value, task.spec, task.defaults.tau_in_termination,
                                 task.defaults.tau_limit)
  print(f"{task.name}: {len(problems)} {_SPLIT.value} demonstrations ({int(annotated.sum())} annotated) -> "
        f"{_OUT.value}")


if __name__ == "__main__":
  flags.mark_flags_as_required(["task", "out"])
  app.run(main, flags_parser=cli.parse_flags)
