r"""Fits a PHP hierarchy to your own demonstrations: no environment code needed.

  python -m experiments.fit --demos=TRAIN.jsonl --hierarchy=H.json --workdir=DIR [--validation=VAL.jsonl]

Reads the hierarchy file and the demonstrations (JSON lines or a binary set; annotated ones carry their call
stack, fully or partly) and trains the hierarchy as the recipe chooses from them: where they leave the
training mode or the segmentation open, each candidate is trained (where one or two demonstrations are annotated,
from two initialisations: --restarts) and the best on the held-out demonstrations (--validation, or else
--validation_fraction of TRAIN, held out at random by --seed) is kept: the one that explains the most, then the
likeliest.
Each training keeps the snapshot that replays the most held-out demonstrations. A demonstration is replayed
when the learned hierarchy's argmax policy, run on its recorded observations, takes every recorded action and
returns from its root after the last. Writes the model (`experiments.decode --policy=DIR` reads it) and
results.json with the held-out replay rate (optimistic: the same demonstrations chose the snapshot and the
candidate) and, with --test, the replay rate of demonstrations that chose nothing. Rerun the same command to
resume an interrupted run.

The file formats (demonstrations, the hierarchy file) and what fit chooses: docs/own-demonstrations.md;
every training flag: docs/training.md.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from absl import app, flags

from experiments.common import cli, config_flags, progress, run_report, training
from php_jax import encoders
from php_jax.data import demo_files, views
from php_jax.demos import Demonstration
from php_jax.envs import gym, replay
from php_jax.training import recipe
from php_jax.training.run import Experiment, train_and_evaluate

_DEMOS = flags.DEFINE_string("demos", None, "Training demonstrations: JSON lines, or a binary set (a directory).")
_HIERARCHY = flags.DEFINE_string("hierarchy", None, "Hierarchy file (JSON): procedure names per level, root "
                                 "first, and the action factor sizes.")
_VALIDATION = flags.DEFINE_string("validation", None, "Held-out demonstrations for choosing the snapshot. "
                                  "Default: --validation_fraction of --demos.")
_ENV = flags.DEFINE_string("env", None, "The Gymnasium environment the demonstrations were recorded in (record's "
                           "--env): the networks' encoders are chosen from its observation space (categories, "
                           "images, words), unless the hierarchy file gives \"observation\". Default: none, the "
                           "observations are read as numbers (or as the hierarchy file's \"observation\" says).")
_TEST = flags.DEFINE_string("test", None, "Demonstrations to measure replay on and nothing else (results.json's "
                            "test_replayed): the held-out ones choose the snapshot and the candidate, so their "
                            "replay rate is optimistic; these choose nothing.")
_VALIDATION_FRACTION = flags.DEFINE_float("validation_fraction", 0.1, "Share of --demos held out when "
                                          "--validation is not given (at least one demonstration).")
_FIT_DEFAULTS = {"hidden": '64, or the hierarchy file\'s "hidden"',
                 "tau_in_termination": '1 at every level, or the hierarchy file\'s "tau_in_termination"',
                 "tau_limit": 'the hierarchy file\'s "tau_limit", else none',
                 "memory": "gru where the observation holds an image, else none",
                 "episode_end": "environment with --env (its episodes end where it ends them), else root",
                 "min_capacity": "where some demonstration is annotated, below the root: the longest annotated call "
                                 "scaled by the longest demonstration over the longest annotated one, at most "
                                 f"{recipe.SPARE_CAPACITY}; or the hierarchy file's \"capacity\""}
config_flags.define_config_flags(lambda name, default: _FIT_DEFAULTS.get(name) or recipe.DEFAULT_TEXT.get(name)
                                 or config_flags.default_text(default))
flags.adopt_module_key_flags(training)
flags.adopt_module_key_flags(config_flags)


def fit_overrides(hierarchy: demo_files.Hierarchy, demos: Demonstration, recorded_in_env: bool) -> dict:
  """A hierarchy file's overrides of the training settings for demos: one hidden layer of 64 (or the file's
  "hidden"), ψ sees τ at every level (or where the file's "tau_in_termination" says), the file's "tau_limit"
  where it gives one, and below the root a counter capacity of at least the file's "capacity"
  (where it gives none and some demonstration is annotated, `recipe.least_capacities`: the longest annotated
  call with room for longer ones in proportion to the demonstrations' lengths), more where an annotated call
  is longer. With nothing annotated and no "capacity", no least capacity: a level is 8 counters wide, or as
  wide as the segmentation's longest call where it annotates it. Where the
  observation holds an image (a view, which seldom shows everything), a memory of the episode (gru). Where
  the demonstrations were recorded in a Gymnasium environment (--env), their ends are the environment's."""
  depth = hierarchy.spec.num_levels
  overrides = {"hidden": hierarchy.hidden or (64,),
               "tau_in_termination": hierarchy.tau_in_termination or (True,) * depth}
  if hierarchy.tau_limit is not None:
    overrides["tau_limit"] = hierarchy.tau_limit
  if any(isinstance(field, encoders.Image) for field in hierarchy.spec.observation or ()):
    overrides["memory"] = "gru"
  if recorded_in_env:
    overrides["episode_end"] = "environment"
  annotated = bool(np.any(demos.strong))
  if annotated or hierarchy.capacity:
    given = hierarchy.capacity or (None,) * depth
    spare = recipe.least_capacities(demos, depth) if annotated else (recipe.SPARE_CAPACITY,) * depth
    overrides["min_capacity"] = (0,) + tuple(s if c is None else c for c, s in zip(given[1:], spare[1:]))
  return overrides


def split(batch: Demonstration, fraction: float, seed: int) -> tuple[Demonstration, Demonstration, tuple[int, ...]]:
  """(training, held out, the training ones' indices in batch): round(fraction × B) demonstrations (at least
  1) held out at random by seed, the weak ones first: an annotated demonstration is held out only where too
  few are weak, so that the few annotations a user has stay in training."""
  num = len(batch.length)
  order = np.random.default_rng(seed).permutation(num)
  order = np.concatenate([order[~batch.strong[order]], order[batch.strong[order]]])
  held = np.zeros(num, bool)
  held[order[:held_out_count(num, fraction)]] = True
  kept, held_out = (views.select(batch, mask) for mask in (~held, held))
  return kept, held_out, tuple(int(b) for b in np.flatnonzero(~held))


def held_out_count(num: int, fraction: float) -> int:
  """How many of num demonstrations `split` holds out: round(fraction × num), at least 1."""
  return max(1, round(fraction * num))


def run() -> dict:
  """Fits the flags' demonstrations; returns the results written to results.json."""
  try:
    hierarchy = demo_files.read_hierarchy(_HIERARCHY.value)
  except demo_files.DemoFileError as e:
    raise config_flags.UsageError(str(e)) from None
  try:
    if _ENV.value and hierarchy.spec.observation is None:
      fields = gym.env_observation_fields(_ENV.value)
      hierarchy = dataclasses.replace(hierarchy, spec=dataclasses.replace(hierarchy.spec, observation=fields))
    demos, spec = demo_files.read_demonstrations(_DEMOS.value, hierarchy.spec)
  except (demo_files.DemoFileError, gym.GymError) as e:
    raise config_flags.UsageError(str(e)) from None
  except ValueError as e:  # the environment's fields beside the hierarchy file's "observes"
    raise config_flags.UsageError(f"--env={_ENV.value}: {e}") from None
  overrides = fit_overrides(hierarchy, demos, bool(_ENV.value))
  config = config_flags.config_from_flags(overrides)
  config_flags.check_levels(hierarchy.spec, config)
  config_flags.check_call_graph(config, demos, spec, f"--demos={_DEMOS.value}")
  shown = run_report.drawn_demonstrations(demos)  # the report's, kept so that it need not read the file again
  shown_demos = views.select(demos, shown)
  try:
    numbers = None
    if _VALIDATION.value:
      held_out, spec = demo_files.read_demonstrations(_VALIDATION.value, spec)
    else:
      if not 0 < _VALIDATION_FRACTION.value < 1:
        raise config_flags.UsageError(f"--validation_fraction must be between 0 and 1; got {_VALIDATION_FRACTION.value}")
      if len(demos.length) < 2:
        raise config_flags.UsageError(f"--demos={_DEMOS.value} has one demonstration: give --validation, or more")
      if held_out_count(len(demos.length), _VALIDATION_FRACTION.value) >= len(demos.length):
        raise config_flags.UsageError(f"--validation_fraction={_VALIDATION_FRACTION.value} holds out all "
                                  f"{len(demos.length)} demonstrations of --demos: lower it, or give --validation")
      demos, held_out, numbers = split(demos, _VALIDATION_FRACTION.value, config.seed)
    tested = None
    if _TEST.value:
      for name, path in (("demos", _DEMOS.value), ("validation", _VALIDATION.value)):
        if path and cli.same_file(_TEST.value, path):
          raise config_flags.UsageError(f"--test={_TEST.value} is the --{name} file: give demonstrations the run "
                                        "does not read")
      tested, spec = demo_files.read_demonstrations(_TEST.value, spec)
  except demo_files.DemoFileError as e:
    raise config_flags.UsageError(str(e)) from None

  def rate(model) -> float:
    return replay.replayed_fraction(model, spec, held_out)

  def test(model) -> dict:
    return {"held_out_replayed": rate(model),
            **({"test_replayed": replay.replayed_fraction(model, spec, tested)} if tested is not None else {})}

  experiment = Experiment(
      spec.name, spec, demos, validate=rate, test=test,
      extra={"demos": _DEMOS.value, "hierarchy": _HIERARCHY.value, "validation": _VALIDATION.value,
             "num_demos": len(demos.length), "num_annotated": int(np.sum(demos.strong)),
             "num_held_out": len(held_out.length), "num_held_out_annotated": int(np.sum(held_out.strong)),
             **({"test_demos": _TEST.value, "num_test": len(tested.length)} if tested is not None else {})},
      action_name=demo_files.action_namer(hierarchy.action_names), numbers=numbers, validation_demos=held_out)
  flat = training.flat_model()
  with progress.shown(config, None if flat else spec.num_levels, training.WORKDIR.value) as echo:
    if flat:
      results = train_and_evaluate(experiment, config, training.WORKDIR.value, training.OVERWRITE.value, flat,
                                   training.WAIT.value, echo)
    else:
      results = training.train_php(experiment, config, config_flags.given_settings(overrides), echo,
                                   recipe.restarts_where_unset(int(np.sum(demos.strong))))
  training.write_report(training.WORKDIR.value, shown_demos, shown)
  return results


def main(argv):
  if len(argv) > 1:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  training.run_resumable(run)


if __name__ == "__main__":
  flags.mark_flags_as_required(["demos", "hierarchy", "workdir"])
  app.run(main, flags_parser=cli.parse_flags)
