r"""Runs a hierarchy on a file of problems and writes one JSON outcome line per problem, in order.

  python -m experiments.evaluate --task=NAME --policy=oracle --problems=IN.jsonl --out=OUT.jsonl

--policy is `oracle` (the supervisor) or a training workdir holding a saved model (PHP or flat baseline). Bad
flags (an --out that is the problem file, a directory or in a missing directory; --batch_size below 1), a
file without problems and a malformed problem line (named by its line number) are reported in one line with
exit status 2 before anything runs; the output file is written atomically, so it is either complete or
absent.
"""
from __future__ import annotations

import json

from absl import app, flags

from experiments.common import cli
from experiments.common import problems as problem_files
from php_jax.data import files
from php_jax.envs import evaluation, tasks
from php_jax.envs.task import Task
from php_jax.training import checkpoint

_TASK = flags.DEFINE_string("task", None, f"The task: one of {', '.join(tasks.TASKS)}, or module:attribute of "
                            "a php_jax.envs.task.Task defined elsewhere.")
_POLICY = flags.DEFINE_string("policy", "oracle", "'oracle' or a workdir with a trained model.")
_PROBLEMS = flags.DEFINE_string("problems", None, "Input JSON-lines file of problems.")
_OUT = flags.DEFINE_string("out", None, "Output JSON-lines file of outcomes.")
_BATCH_SIZE = flags.DEFINE_integer("batch_size", 64, "Problems rolled out together.", lower_bound=1)


def load_policy(task_name: str, task: Task, policy: str):
  """The oracle, or the model (PHP hierarchy or flat baseline) saved in a workdir for the same task."""
  if policy == "oracle":
    return task.oracle
  saved_task, model = checkpoint.load_policy(policy)
  if saved_task != task_name:
    raise ValueError(f"--policy={policy!r} holds a {saved_task} model, not {task_name}")
  return model


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    cli.check_outputs({"out": _OUT.value}, {"problems": _PROBLEMS.value,
                                            "policy": None if _POLICY.value == "oracle" else _POLICY.value})
    task = tasks.get(_TASK.value)
    try:
      problems = problem_files.read_problems(_PROBLEMS.value, task)
    except OSError as e:
      raise ValueError(f"--problems={_PROBLEMS.value}: {e.strerror or e}") from None
    policy = load_policy(_TASK.value, task, _POLICY.value)
  except (OSError, ValueError) as e:  # ProblemFileError and CheckpointError are ValueErrors
    cli.fail(str(e))
  outcomes = evaluation.solve(task, policy, problems, batch_size=_BATCH_SIZE.value)
  with cli.output_errors("out", _OUT.value):
    files.write_atomically(_OUT.value, "".join(json.dumps(o) + "\n" for o in outcomes).encode())
  correct = sum(o["correct"] for o in outcomes)
  print(f"{task.name}: {correct}/{len(outcomes)} correct -> {_OUT.value}")


if __name__ == "__main__":
  flags.mark_flags_as_required(["task", "problems", "out"])
  app.run(main, flags_parser=cli.parse_flags)
