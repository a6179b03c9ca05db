r"""Which demonstrations to annotate: ranks the actions-only ones by what annotating them would add.

  python -m experiments.suggest --demos=FILE.jsonl --hierarchy=H.json --budget=K --out=OUT.jsonl [--policy=RUN]
  python -m experiments.suggest --task=NAME --seed=S [--num_demos=M] --budget=K --out=OUT.jsonl

The first form reads your demonstration file (demonstrations already annotated count as chosen); the second
takes a registered task's training set as `experiments.train --seed=S` builds it, none annotated. Each of
the --budget chosen demonstrations, best first, is one output line {"index": its 0-based line number (or
index in the task's training set), "score": its number of steps (with --policy: the model's summed
uncertainty over them), "why": in words}. While some behaviour the demonstrations show (the action values
and pairs of consecutive actions they take) is shown by no annotated or earlier chosen one, the next is the
longest that shows some of it; then the longest of the others (`php_jax.analysis.annotation_choice`). With --policy,
a trained hierarchy's uncertainty about each demonstration's segmentation ranks instead of its length.
Annotate the chosen ones (in your file), or give the output to `experiments.train --annotate=OUT.jsonl`.
The file formats: docs/own-demonstrations.md.
"""
from __future__ import annotations

import dataclasses
import json

from absl import app, flags

from experiments.common import cli, run_view
from php_jax.analysis import annotation_choice
from php_jax.data import demo_files, files, shards
from php_jax.envs import datasets, tasks
from php_jax.training.config import MAX_SEED

_DEMOS = flags.DEFINE_string("demos", None, "Demonstrations (JSON lines, or a binary set), some perhaps annotated.")
_HIERARCHY = flags.DEFINE_string("hierarchy", None, "Their hierarchy file (with --demos).")
_TASK = flags.DEFINE_string("task", None, "A registered task (or module:attribute) whose training set to rank, "
                            "instead of --demos.")
_SEED = flags.DEFINE_integer("seed", 0, "With --task: the seed of the training set (experiments.train's --seed).",
                             lower_bound=0)
_NUM_DEMOS = flags.DEFINE_integer("num_demos", None, "With --task: demonstrations in the training set, where the "
                                  "task offers a choice. Default: the task's.", upper_bound=datasets.MOST_DEMOS)
_POLICY = flags.DEFINE_string("policy", None, "Optional: a trained hierarchy's workdir; its uncertainty about "
                              "each demonstration's segmentation ranks instead of the length.")
_BUDGET = flags.DEFINE_integer("budget", None, "How many demonstrations to choose.", lower_bound=1)
_OUT = flags.DEFINE_string("out", None, "Output JSON-lines file, best first.")


def _task_demos():
  """The task's training set (none annotated) and its action namer."""
  task = tasks.get(_TASK.value)
  num_demos = task.defaults.num_demos if _NUM_DEMOS.value is None else _NUM_DEMOS.value
  if task.defaults.num_demos_fixed and num_demos != task.defaults.num_demos:
    raise ValueError(f"--num_demos: {task.name}'s training set has {task.defaults.num_demos} demonstrations; got "
                     f"{num_demos}")
  if num_demos < 1:
    raise ValueError(f"--num_demos must be positive; got {num_demos}")
  return datasets.training_demos(task, _SEED.value, num_demos, 0), task.spec, task.action_name


def _file_demos():
  """The file's demonstrations and their action namer."""
  if not _HIERARCHY.value:
    raise ValueError("--demos needs --hierarchy")
  hierarchy = demo_files.read_hierarchy(_HIERARCHY.value)
  demos, spec = demo_files.read_demonstrations(_DEMOS.value, hierarchy.spec)
  return demos, spec, demo_files.action_namer(hierarchy.action_names)


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    if bool(_DEMOS.value) == bool(_TASK.value):
      raise ValueError("give --demos (with --hierarchy) or --task, one of them")
    given = [f"--{name}" for name in ("hierarchy", "seed", "num_demos") if flags.FLAGS[name].present]
    wrong = [g for g in given if (g == "--hierarchy") == bool(_TASK.value)]
    if wrong:
      raise ValueError(f"{wrong[0]} goes with {'--demos' if _TASK.value else '--task'}, not "
                       f"{'--task' if _TASK.value else '--demos'}")
    if _SEED.value > MAX_SEED:
      raise ValueError(f"--seed must be at most {MAX_SEED}; got {_SEED.value}")
    cli.check_outputs({"out": _OUT.value}, {"demos": _DEMOS.value, "hierarchy": _HIERARCHY.value,
                                          "policy": _POLICY.value})
    demos, spec, action_name = _task_demos() if _TASK.value else _file_demos()
    doubt = None
    if _POLICY.value:
      run = run_view.load(_POLICY.value)
      if run.hierarchy.spec.levels != spec.levels or run.hierarchy.spec.obs_dim != spec.obs_dim:
        raise ValueError(f"--policy={_POLICY.value} is a hierarchy of other levels or observation size")
      doubt = annotation_choice.uncertainty(run.hierarchy, run.capacity, demos)
    if demos.strong.all():
      raise ValueError(f"--demos={_DEMOS.value}: every demonstration is annotated already; nothing to choose")
  except (OSError, ValueError) as e:  # DemoFileError and CheckpointError are ValueErrors
    cli.fail(str(e))
  chosen = annotation_choice.suggest(demos, _BUDGET.value, action_name, doubt)
  lines = "".join(json.dumps(dataclasses.asdict(s)) + "\n" for s in chosen)
  with cli.output_errors("out", _OUT.value):
    files.write_atomically(_OUT.value, lines.encode())
  in_lines = _DEMOS.value and not shards.read_as_binary(_DEMOS.value)  # a binary set has no lines to name
  for rank, s in enumerate(chosen, 1):
    line = f" (line {s.index + 1} of {_DEMOS.value})" if in_lines else ""
    print(f"{rank}. demonstration {s.index}{line}: {s.why}")
  print(f"{len(chosen)} of {int((~demos.strong).sum())} actions-only demonstrations chosen -> {_OUT.value}")


if __name__ == "__main__":
  flags.mark_flags_as_required(["budget", "out"])
  app.run(main, flags_parser=cli.parse_flags)
