r"""Trains a PHP hierarchy (or the flat LSTM baseline) on any task from its supervisor's demonstrations.

  python -m experiments.train --task=NAME --workdir=DIR --num_strong=N --seed=S [--num_demos=M]
  python -m experiments.train --task=NAME --workdir=DIR --num_strong=N --seeds=1,2,3,4,5

Builds the task's training set for --seed (num_strong of its demonstrations annotated with the whole call
stack, the rest actions only), trains the hierarchy as the recipe chooses (where the task and the flags
leave the training mode or the segmentation open, each candidate, keeping the one most likely on the
validation problems' demonstrations), saves the model (`experiments.evaluate --policy=WORKDIR` runs it) and writes
results.json with the accuracy on fresh test problems (seeds disjoint from training and validation). Rerun
the same command to resume an interrupted run. Flags left unset take the task's defaults.

With --seeds, each seed's run (its own training set, initialisation, snapshot and test) goes to
WORKDIR/seed=S, with the files `--seed=S --workdir=WORKDIR/seed=S` would write; the seeds' updates run as one
vmapped program per level (`php_jax.training.levelwise.train_seeds`). Every flag, and what each training mode
does: docs/training.md; what a run writes: docs/outputs.md.
"""
from __future__ import annotations

import dataclasses
import os

import numpy as np
from absl import app, flags

from experiments.common import cli, config_flags, progress, training
from php_jax.data import demo_files
from php_jax.envs import datasets, evaluation, tasks
from php_jax.training import levelwise, recipe
from php_jax.training.run import Experiment, train_and_evaluate, train_and_evaluate_seeds
from php_jax.training.config import TrainConfig

NUM_STRONG = flags.DEFINE_integer("num_strong", 1, "Strongly supervised (call-stack annotated) demonstrations.")
NUM_VALIDATION = flags.DEFINE_integer("num_validation", 50, "Validation problems (training distribution).")
_ANNOTATE = flags.DEFINE_string("annotate", None, "Which training demonstrations are annotated: the \"index\" of "
                                "each line of this file (experiments.suggest's output), instead of --num_strong "
                                "chosen at random.")
SEEDS = flags.DEFINE_list("seeds", None, "Several seeds (e.g. 1,2,3,4,5) trained as one program, level-wise: "
                          "each seed's run, the same as with --seed, goes to WORKDIR/seed=S.")
_TASK = flags.DEFINE_string("task", None, f"The task: one of {', '.join(tasks.TASKS)}, or module:attribute "
                            "of a php_jax.envs.task.Task defined elsewhere.")


def _per_task(value) -> str:
  """The registered tasks' values of a training-set default, for --help."""
  return "; ".join(f"{task.name}: {value(task.defaults)}" for task in tasks.TASKS.values())


_NUM_DEMOS = flags.DEFINE_integer("num_demos", None, "Demonstrations in the training set, where the task offers "
                                  "a choice. Default: the task's (" + _per_task(
                                      lambda d: d.num_demos if not d.num_demos_fixed else f"{d.num_demos}, fixed")
                                  + ").", upper_bound=datasets.MOST_DEMOS)
_TEST_LENGTHS = flags.DEFINE_list("test_lengths", None, "Problem sizes of the test sets (e.g. digits, array "
                                  "lengths). Default: the task's (" + _per_task(
                                      lambda d: ",".join(map(str, d.test_lengths or ())) or "one set") + ").")
_NUM_TEST = flags.DEFINE_integer("num_test", None, "Test problems per test set. Default: the task's ("
                                 + _per_task(lambda d: d.num_test) + ").")


def _task_defaults(name: str, default) -> str:
  """A setting's default as --help shows it: TrainConfig's (or the recipe's), and the registered tasks that
  override it."""
  return config_flags.default_text(recipe.DEFAULT_TEXT.get(name, default),
                                   {task.name: task.defaults.overrides()[name] for task in tasks.TASKS.values()
                                    if name in task.defaults.overrides()})


config_flags.define_config_flags(_task_defaults)
flags.adopt_module_key_flags(training)
flags.adopt_module_key_flags(config_flags)


def run(task_name: str) -> dict:
  """Trains and tests on task_name with the flags' settings; returns the results written to results.json."""
  try:
    task = tasks.get(task_name)
  except ValueError as e:
    raise config_flags.UsageError(f"--task: {e}") from None
  defaults = task.defaults
  num_demos = defaults.num_demos if _NUM_DEMOS.value is None else _NUM_DEMOS.value
  if defaults.num_demos_fixed and num_demos != defaults.num_demos:
    raise config_flags.UsageError(f"--num_demos: {task.name}'s training set has {defaults.num_demos} "
                              f"demonstrations; got {num_demos}")
  if num_demos < 1 or not 0 <= NUM_STRONG.value <= num_demos:
    raise config_flags.UsageError(f"--num_strong must be in 0..--num_demos={num_demos} and --num_demos ≥ 1; got "
                              f"{NUM_STRONG.value} of {num_demos}")
  num_test = defaults.num_test if _NUM_TEST.value is None else _NUM_TEST.value
  lengths = defaults.test_lengths
  if _TEST_LENGTHS.value is not None:
    if not (_TEST_LENGTHS.value and all(n.isdigit() for n in _TEST_LENGTHS.value)):
      raise config_flags.UsageError(f"--test_lengths must list positive integers; got {','.join(_TEST_LENGTHS.value)}")
    lengths = [int(n) for n in _TEST_LENGTHS.value]
  if num_test < 1 or any(n < 1 for n in lengths):
    raise config_flags.UsageError(f"--num_test and --test_lengths must be positive; got {num_test}, {list(lengths)}")
  annotated = _annotated(num_demos)
  overrides = defaults.overrides(bool(NUM_STRONG.value if annotated is None else annotated))
  config = config_flags.config_from_flags(overrides)
  config_flags.check_levels(task.spec, config)
  if NUM_VALIDATION.value < 1:
    raise config_flags.UsageError(f"--num_validation must be a positive integer; got {NUM_VALIDATION.value}")
  workdir, overwrite, wait = training.WORKDIR.value, training.OVERWRITE.value, training.WAIT.value
  flat = training.flat_model()
  if SEEDS.value is None:
    experiment = _experiment(task_name, task, config.seed, num_demos, num_test, lengths, annotated)
    config_flags.check_call_graph(config, experiment.demos, task.spec, f"--call_graph={config.call_graph}")
    with progress.shown(config, None if flat else task.spec.num_levels, workdir) as echo:
      if flat:
        results = train_and_evaluate(experiment, config, workdir, overwrite, flat, wait, echo)
      else:
        results = training.train_php(experiment, config, config_flags.given_settings(overrides), echo)
    training.write_report(workdir, experiment.demos)
    return results
  seeds = _seeds(config)
  experiments = [_experiment(task_name, task, s, num_demos, num_test, lengths, annotated) for s in seeds]
  try:
    levelwise.common_call_graph(task.spec, [e.demos for e in experiments], [config] * len(seeds))
  except ValueError as e:
    raise config_flags.UsageError(f"--seeds: {e}") from None
  with progress.shown(config, task.spec.num_levels, workdir) as echo:
    results = train_and_evaluate_seeds(experiments, [dataclasses.replace(config, seed=s) for s in seeds], workdir,
                                       overwrite, wait, echo)
  for seed, experiment in zip(seeds, experiments):
    training.write_report(os.path.join(workdir, f"seed={seed}"), experiment.demos)
  return results


def _seeds(config: TrainConfig) -> list[int]:
  """--seeds' values, checked against the other flags."""
  if flags.FLAGS["seed"].present:
    raise config_flags.UsageError("--seeds and --seed: give one of them")
  if training.MODEL.value != "php":
    raise config_flags.UsageError(f"--seeds trains PHP hierarchies (not --model={training.MODEL.value})")
  if config.training == "joint":
    raise config_flags.UsageError(config_flags.joint_refusal("--seeds trains level-wise only"))
  if (training.RESTARTS.value or 1) > 1:
    raise config_flags.UsageError("--seeds and --restarts: give one of them (--seeds trains one run per seed)")
  try:
    return cli.seed_list(SEEDS.value)
  except ValueError as e:
    raise config_flags.UsageError(str(e)) from None


def _annotated(num_demos: int) -> list[int] | None:
  """The training demonstrations --annotate names (None without it); UsageError naming the file's problem."""
  if _ANNOTATE.value is None:
    return None
  if flags.FLAGS["num_strong"].present:
    raise config_flags.UsageError("--annotate and --num_strong: give one of them")
  try:
    indices = demo_files.read_indices(_ANNOTATE.value, num_demos)
  except demo_files.DemoFileError as e:
    raise config_flags.UsageError(f"--annotate: {e}") from None
  return indices


def _experiment(task_name: str, task, seed: int, num_demos: int, num_test: int, lengths,
                annotated: list[int] | None) -> Experiment:
  """Seed's run of task (named task_name on the command line): its training demonstrations (annotated: which
  are; None: --num_strong at random), validation and test sets, results.json entries."""
  demos = datasets.training_demos(task, seed, num_demos, NUM_STRONG.value)
  if annotated is not None:
    strong = np.zeros(num_demos, bool)
    strong[annotated] = True
    demos = demos._replace(strong=strong)
  validation = task.validation_problems(seed + datasets.SEED_OFFSETS["validation"], NUM_VALIDATION.value)
  test_seed = seed + datasets.SEED_OFFSETS["test"]
  test_sets = ({str(n): task.test_problems(test_seed, num_test, n) for n in lengths} if lengths
               else {"accuracy": task.test_problems(test_seed, num_test, None)})
  return Experiment(task_name, task.spec, demos, lambda model: evaluation.accuracy(task, model, validation),
                    lambda model: {key: evaluation.accuracy(task, model, problems)
                                   for key, problems in test_sets.items()},
                    {"seed": seed, "num_demos": num_demos, "num_strong": int(demos.strong.sum()),
                     "num_test": num_test, **({"annotated": annotated} if annotated is not None else {})},
                    action_name=task.action_name,
                    validation_demos=datasets.problem_demonstrations(task, validation, 0))


def main_for(task_name: str | None):
  """An absl main that trains task_name (None: the --task flag's)."""
  def main(argv):
    if len(argv) > 1:
      cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
    name = task_name or _TASK.value
    if not name:
      cli.fail("--task is required")
    training.run_resumable(lambda: run(name))
  return main


if __name__ == "__main__":
  flags.mark_flags_as_required(["workdir"])
  app.run(main_for(None), flags_parser=cli.parse_flags)
