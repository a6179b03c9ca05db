r"""Records an expert's episodes in a Gymnasium environment as a demonstration file for `experiments.fit`.

  python -m experiments.record --env=ENV --expert=MODULE:ATTR --episodes=N --annotated=K --seed=S \
      --out=FILE.jsonl [--hierarchy=H.json]
  python -m experiments.record ... --annotate=SUGGESTED.jsonl   # stacks on the episodes suggest chose

ENV is a registered Gymnasium id (`Taxi-v3`) or MODULE:ATTR, a callable returning a gymnasium.Env. The
expert's MODULE:ATTR is a callable that takes the environment and returns an object with
`act(observation, info)` (an action, or `(action, stack)` with the call stack that chose it) and optionally
`reset(observation, info)`; see php_jax.envs.gym. Episode i is reset with seed S + i; the first K episodes keep
their call stacks (with --annotate instead: the episodes whose "index" its lines give, as
`experiments.suggest` writes them), the others are actions only. A stack that breaks the call-stack rules
(or, with --hierarchy, names a procedure the hierarchy does not have) is refused naming the episode and
step; every refusal is one line with exit status 2 and nothing written. --out's folder is made if missing;
an --out ending in .shards is written as a binary set (a directory of shards, for large data sets). Each
episode is written as it ends, into a temporary file put in place after the last, so memory holds one episode
(or one shard), however many are recorded; interrupted, the command leaves nothing.

The expert sees the environment's own observations (a dict stays a dict); the file holds them flattened
(`gymnasium.spaces.flatten`). The closing lines say how the expert did: its success rate under --success
(or that success is unknown, as in `experiments.act`), its mean return and how its episodes ended. The expert
and the file format: docs/own-environment.md and docs/own-demonstrations.md.
"""
from __future__ import annotations

import gymnasium
from absl import app, flags

from experiments.common import cli, environment_flags, progress
from php_jax.data import demo_files
from php_jax.envs import gym, success

_EXPERT = flags.DEFINE_string("expert", None, "module:attribute of a callable that takes the environment and "
                              "returns the expert.")
_EPISODES = flags.DEFINE_integer("episodes", None, "Episodes to record.", lower_bound=1)
_ANNOTATED = flags.DEFINE_integer("annotated", 0, "How many of the first episodes keep the expert's call "
                                  "stacks.", lower_bound=0)
_ANNOTATE = flags.DEFINE_string("annotate", None, "Which episodes keep the expert's call stacks: the \"index\" "
                                "(0-based) of each line of this file (experiments.suggest's output), instead of "
                                "--annotated.")
_OUT = flags.DEFINE_string("out", None, "Output demonstration file: JSON lines, or a binary set where it ends in "
                           ".shards.")
_HIERARCHY = flags.DEFINE_string("hierarchy", None, "Optional hierarchy file: stacks are also checked "
                                 "against its procedures.")

flags.adopt_module_key_flags(environment_flags)


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    cli.check_outputs({"out": _OUT.value}, {"hierarchy": _HIERARCHY.value, "annotate": _ANNOTATE.value},
                      make_folders=True, demo_sets=True)
    rule = environment_flags.success_rule()
    if _ANNOTATED.value > _EPISODES.value:
      raise ValueError(f"--annotated={_ANNOTATED.value} is more than --episodes={_EPISODES.value}")
    if _ANNOTATE.value is not None and flags.FLAGS["annotated"].present:
      raise ValueError("--annotate and --annotated: give one of them")
    annotate = _annotate()
    spec = demo_files.read_hierarchy(_HIERARCHY.value).spec if _HIERARCHY.value else None
    env = gym.env_maker(environment_flags.ENV.value)()
    if environment_flags.MAX_STEPS.value is not None:
      env = gymnasium.wrappers.TimeLimit(env, environment_flags.MAX_STEPS.value)
    expert = gym.expert_maker(_EXPERT.value)(env)
    if spec is not None and spec.action_sizes != gym.action_sizes(env.action_space):
      raise ValueError(f"--hierarchy={_HIERARCHY.value} has action factor sizes {list(spec.action_sizes)}; "
                       f"--env={environment_flags.ENV.value}'s {env.action_space} has "
                       f"{list(gym.action_sizes(env.action_space))}")
  except (OSError, ValueError) as e:  # GymError and DemoFileError are ValueErrors
    cli.fail(str(e))
  endings, counts = [], {"steps": 0, "annotated": 0}

  def ended(ending: success.Ending) -> None:
    endings.append(ending)
    on_episode()

  def counted(lines):  # the recording's own failures told apart from --out's
    try:
      for line in lines:
        counts["steps"] += len(line["actions"])
        counts["annotated"] += "stack" in line
        yield line
    except (OSError, ValueError) as e:
      raise _RecordingError(str(e)) from None

  try:
    with progress.counting(_EPISODES.value, "episodes") as on_episode, cli.output_errors("out", _OUT.value):
      gym.write_demonstrations(_OUT.value, counted(gym.recorded(
          env, expert, _EPISODES.value, environment_flags.SEED.value,
          _ANNOTATED.value if annotate is None else annotate, spec, ended)))
  except (_RecordingError, ValueError) as e:  # ValueError: episodes of other shapes than the first's
    cli.fail(str(e))
  print(f"{len(endings)} episodes ({counts['annotated']} annotated), {counts['steps']} steps -> {_OUT.value}")
  print("the expert: " + "\n".join(success.summary(rule, endings)))


class _RecordingError(Exception):
  """The recording failed (the expert, the environment, a stack), not the writing of --out."""


def _annotate() -> list[int] | None:
  """The episodes --annotate names (None without it); ValueError naming the file's problem."""
  if _ANNOTATE.value is None:
    return None
  try:
    return demo_files.read_indices(_ANNOTATE.value, _EPISODES.value)
  except demo_files.DemoFileError as e:
    raise ValueError(f"--annotate: {e}") from None


if __name__ == "__main__":
  flags.mark_flags_as_required(["env", "expert", "episodes", "out"])
  app.run(main, flags_parser=cli.parse_flags)
