r"""Long-hand addition (paper §5.2): 160 traces, 16 per length 1..10, num_strong of them annotated.

  python -m experiments.addition --workdir=runs/add10 --num_strong=10 --seed=1

Trains all three levels, saves the model (evaluate with --policy=WORKDIR) and writes results.json with the
accuracy on fresh problems at each --test_lengths (seeds disjoint from training and validation).
"""
from __future__ import annotations

from absl import app, flags

from experiments import training
from php_jax import datasets, evaluation, tasks

_TEST_LENGTHS = flags.DEFINE_list("test_lengths", ["20", "100"], "Digits of the test problems.")
_NUM_TEST = flags.DEFINE_integer("num_test", 100, "Test problems per length.")
DEFAULT_TAU_IN_TERMINATION = (False, True, True)  # add's ψ needs no counter; add1's and the lowest's do
DEFAULT_HIDDEN = (64,)  # one layer: solved every test length with 1, 3, 10 strong; twice as fast as (64, 64)


def main(argv):
  del argv
  seed, task = training.SEED.value, tasks.get("addition")
  demos = datasets.addition_training_demos(seed, training.NUM_STRONG.value)
  validation = datasets.random_addition_problems(seed + 10_000, range(1, 11),
                                                max(1, training.NUM_VALIDATION.value // 10))
  lengths = [int(n) for n in _TEST_LENGTHS.value]
  test_sets = {n: datasets.random_addition_problems(seed + 20_000 + n, [n], _NUM_TEST.value)
               for n in lengths}
  test = lambda h: {str(n): evaluation.accuracy(h, task.spec, problems) for n, problems in test_sets.items()}
  training.train_and_evaluate(
      "addition", demos, training.config_from_flags(DEFAULT_TAU_IN_TERMINATION, DEFAULT_HIDDEN),
      training.WORKDIR.value,
      validate=lambda h: evaluation.accuracy(h, task.spec, validation), test=test,
      extra={"seed": seed, "num_demos": len(demos.strong), "num_strong": int(demos.strong.sum()),
             "num_test": _NUM_TEST.value})


if __name__ == "__main__":
  flags.mark_flags_as_required(["workdir"])
  app.run(main)
