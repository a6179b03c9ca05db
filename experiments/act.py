r"""Runs a fitted policy in a Gymnasium environment: one JSON line per episode, then its success rate.

  python -m experiments.act --policy=RUN --env=ENV --episodes=N --seed=S [--num_envs=M] --out=FILE.jsonl

--policy is a workdir of `experiments.fit` (a PHP hierarchy or a flat baseline); ENV as in `experiments.record`.
Episode i is reset with seed S + i. A hierarchy acts by the executor's semantics (greedy, or with --sample
drawing its operations and terminations): it pushes its root, descends on the first observation, and after
every action pops the procedures that terminate and resumes the one below them; the episode ends when the
environment ends it, or when the root returns. A flat baseline steps its recurrent cell and stops or acts (greedy,
or with --sample drawing its actions and its stop). With --num_envs, M copies of the environment run side by
side (a gymnasium.vector environment) and each step's decisions for all of them are one compiled call. Each
line, in episode order:

  {"return": float, "steps": int,
   "success": bool or null,             under --success; without it, info["is_success"] at the end where
                                        the environment reports it, else null (unknown)
   "terminated": bool, "truncated": bool,
   "stack": [[[h, tau], ...], ...]}     per step, root first: the call stack that chose the action (null
                                        for a flat baseline)

The closing lines give the success rate and the rule it was judged by (or say that success is unknown and
how to define it), the mean return, and how many episodes the environment terminated or truncated and how
many the policy ended. Gymnasium does not define success, and termination is not it: FrozenLake ends in a
hole and BabyAI ends failed missions too. See docs/own-environment.md.

A policy whose observation or action sizes are not the environment's, a bad flag or an unknown environment
ends in one line with exit status 2 before anything runs; the output is written atomically.
"""
from __future__ import annotations

import json
import time

from absl import app, flags

from experiments.common import cli, environment_flags, progress
from php_jax.data import files
from php_jax.envs import gym, success
from php_jax.training import checkpoint

_POLICY = flags.DEFINE_string("policy", None, "Workdir of experiments.fit holding the policy.")
_EPISODES = flags.DEFINE_integer("episodes", 100, "Episodes to run.", lower_bound=1)
_NUM_ENVS = flags.DEFINE_integer("num_envs", 1, "Copies of the environment stepped together.", lower_bound=1,
                                 upper_bound=4096)
_OUT = flags.DEFINE_string("out", None, "Output JSON-lines file, one line per episode.")
_SAMPLE = flags.DEFINE_bool("sample", False, "Draw each choice from the policy's distribution instead of taking "
                            "the most likely (a hierarchy: operations and terminations; a flat baseline: actions and "
                            "its stop); episode i's step t folds i and t into --seed's key.")

flags.adopt_module_key_flags(environment_flags)


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    cli.check_outputs({"out": _OUT.value}, {"policy": _POLICY.value})
    rule = environment_flags.success_rule()
    _, policy = checkpoint.load_policy(_POLICY.value)
    policy.sample = _SAMPLE.value
    envs = gym.vector_env(gym.env_maker(environment_flags.ENV.value), _NUM_ENVS.value)
    try:
      gym.check_policy(policy, envs.single_observation_space, envs.single_action_space)
    except gym.GymError as e:
      raise ValueError(f"--policy={_POLICY.value} does not fit --env={environment_flags.ENV.value}: {e}"
                       ) from None
  except (OSError, ValueError) as e:  # GymError and CheckpointError are ValueErrors
    cli.fail(str(e))
  start = time.perf_counter()
  endings = []
  try:
    with progress.counting(_EPISODES.value, "episodes") as on_episode:
      def ended(ending: success.Ending) -> None:
        endings.append(ending)
        on_episode()

      episodes = gym.act(policy, envs, _EPISODES.value, environment_flags.SEED.value,
                         environment_flags.MAX_STEPS.value, ended, rule)
  except gym.GymError as e:  # the environment failed, or gave an observation that is not finite
    cli.fail(f"{e}; --out={_OUT.value} not written")
  seconds = time.perf_counter() - start
  with cli.output_errors("out", _OUT.value):
    files.write_atomically(_OUT.value, "".join(json.dumps(e) + "\n" for e in episodes).encode())
  steps = sum(e["steps"] for e in episodes)
  print(f"{len(episodes)} episodes, {steps} steps in {seconds:.1f} s -> {_OUT.value}")
  print("\n".join(success.summary(rule, endings)))


if __name__ == "__main__":
  flags.mark_flags_as_required(["policy", "env", "out"])
  app.run(main, flags_parser=cli.parse_flags)
