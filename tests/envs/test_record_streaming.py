"""`record` writes episodes as they end: its memory holds one episode (or one shard), not the recording; a
recording that fails or is interrupted leaves no file and no part of one."""
import pathlib
import signal
import subprocess
import sys
import time
import tracemalloc

import gymnasium
import numpy as np
import pytest

from php_jax.data import demo_files, shards
from php_jax.envs import gym
from php_jax.hierarchy import HierarchySpec

ROOT = pathlib.Path(__file__).resolve().parents[2]


class Wide(gymnasium.Env):
  """Ten steps of a 1,000-number observation; any action."""
  observation_space = gymnasium.spaces.Box(-1.0, 1.0, (1000,), np.float32)
  action_space = gymnasium.spaces.Discrete(2)

  def __init__(self, seconds_per_step: float = 0.0):
    self.seconds_per_step, self.t = seconds_per_step, 0

  def reset(self, seed=None, options=None):
    super().reset(seed=seed)
    self.t = 0
    return self.np_random.uniform(-1, 1, 1000).astype(np.float32), {}

  def step(self, action):
    time.sleep(self.seconds_per_step)
    self.t += 1
    return self.np_random.uniform(-1, 1, 1000).astype(np.float32), 0.0, self.t == 10, False, {}


def make_slow() -> gymnasium.Env:
  return Wide(seconds_per_step=0.02)


class FirstAction:
  def __init__(self, env):
    pass

  def act(self, observation, info):
    return 0


def _peak_memory(write) -> int:
  """The most memory Python held while write() ran (tracemalloc), in bytes."""
  tracemalloc.start()
  try:
    write()
    return tracemalloc.get_traced_memory()[1]
  finally:
    tracemalloc.stop()


@pytest.mark.parametrize("suffix", [".jsonl", shards.SUFFIX])
def test_recording_holds_one_episode_at_a_time_and_writes_what_record_returns(tmp_path, suffix):
  """Written as the episodes end, a recording takes a small part of the memory that recording every episode
  first (`record`, then writing its lines) takes, and writes the same file (a binary set: one shard's worth
  at a time, here 10 episodes)."""
  env, episodes = Wide(), 100
  streamed, whole = tmp_path / f"streamed{suffix}", tmp_path / f"whole{suffix}"
  streaming = _peak_memory(lambda: gym.write_demonstrations(
      str(streamed), gym.recorded(env, FirstAction(env), episodes, seed=3), shard_size=10))
  first_all = _peak_memory(lambda: gym.write_demonstrations(
      str(whole), gym.record(env, FirstAction(env), episodes, seed=3), shard_size=10))
  assert streaming < first_all / 5, (streaming, first_all)
  spec = HierarchySpec("wide", (("root",), ("step",)), (2,), 0)
  read = [demo_files.read_demonstrations(str(p), spec)[0] for p in (streamed, whole)]
  assert len(read[0].length) == episodes
  for a, b in zip(*read):
    np.testing.assert_array_equal(a, b)


@pytest.mark.parametrize("suffix", [".jsonl", shards.SUFFIX])
def test_an_interrupted_recording_ends_at_once_leaving_nothing(tmp_path, suffix):
  out = tmp_path / f"out{suffix}"
  proc = subprocess.Popen([sys.executable, "-m", "experiments.record",
                           "--env=tests.envs.test_record_streaming:make_slow",
                           "--expert=tests.envs.test_record_streaming:FirstAction", "--episodes=1000", f"--out={out}"],
                          stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True, cwd=ROOT)
  deadline = time.time() + 120
  while not list(tmp_path.glob(f".{out.name}.*.tmp")) and time.time() < deadline:  # recording into it
    time.sleep(0.1)
  time.sleep(1.0)
  assert list(tmp_path.glob(f".{out.name}.*.tmp")) and proc.poll() is None
  proc.send_signal(signal.SIGTERM)
  _, stderr = proc.communicate(timeout=30)
  assert proc.returncode == 130 and "interrupted" in stderr, stderr
  assert list(tmp_path.iterdir()) == []


def test_a_recording_that_fails_midway_writes_nothing(tmp_path):
  class FailsAtEpisode3(FirstAction):
    episodes = 0

    def reset(self, observation, info):
      FailsAtEpisode3.episodes += 1

    def act(self, observation, info):
      if FailsAtEpisode3.episodes == 4:
        raise RuntimeError("lost")
      return 0

  env = Wide()
  for out in (tmp_path / "out.jsonl", tmp_path / f"out{shards.SUFFIX}"):
    FailsAtEpisode3.episodes = 0
    with pytest.raises(gym.GymError, match="episode 3, step 0: the expert's act"):
      gym.write_demonstrations(str(out), gym.recorded(env, FailsAtEpisode3(env), 10, seed=0))
  assert list(tmp_path.iterdir()) == []
