"""Training settings written once: TrainConfig's checks, the flags generated from its fields, task overrides."""
import dataclasses
import pathlib
import subprocess
import sys

import jax
import numpy as np
import pytest
from absl import flags
from flax import nnx

from experiments.common import config_flags
from php_jax.envs import tasks
from php_jax.training import config as config_lib, networks

ROOT = pathlib.Path(__file__).resolve().parents[2]


def _flags(*argv: str, defaults=lambda name, default: config_flags.default_text(default)) -> flags.FlagValues:
  values = flags.FlagValues()
  config_flags.define_config_flags(defaults, values)
  values(["prog", *argv])
  return values


def test_every_field_has_a_flag_with_its_help_and_default():
  values = _flags()
  for field in config_lib.fields():
    flag = values[field.name]
    assert flag.value is None and field.metadata["help"] in flag.help
  assert "Default: 2000." in values["iterations"].help
  assert "Default:" not in values["strong_weight"].help  # unset: its help says what that means


def test_help_shows_the_tasks_overrides():
  overrides = {task.name: task.defaults.overrides()["iterations"] for task in tasks.TASKS.values()
               if "iterations" in task.defaults.overrides()}
  assert overrides == {"bubblesort": 1000}
  assert config_flags.default_text(2000, overrides) == "2000 (bubblesort: 1000)"
  assert config_flags.default_text(None, {"bubblesort": (0, 1, None)}) == "unset (bubblesort: 0,1,none)"


def test_flags_override_the_task_which_overrides_the_defaults():
  bubblesort = tasks.get("bubblesort").defaults.overrides()
  config = config_flags.config_from_flags(bubblesort, _flags("--iterations=7", "--tau_in_termination=1,0,1"))
  assert (config.iterations, config.tau_in_termination, config.hidden, config.training) == (
      7, (True, False, True), (64,), "levelwise")
  assert config.call_graph == config_lib.TrainConfig().call_graph  # neither the task nor a flag set it
  assert config_flags.config_from_flags({}, _flags("--tau_limit=0,none,3")).tau_limit == (0, None, 3)


@pytest.mark.parametrize("argv, message", [
    (["--hidden="], "--hidden must list integers; got ''"),
    (["--hidden=8,x"], "--hidden must list integers; got '8,x'"),
    (["--tau_in_termination=1,maybe"], "--tau_in_termination must list 0/1 (or true/false)"),
    (["--call_penalty=0,nan"], "--call_penalty: must list one finite non-negative number per level"),
    (["--seed=-1"], "--seed: must be a non-negative integer; got -1"),
    (["--init_seed=-1"], "--init_seed: must be a non-negative integer; got -1"),
    (["--iterations=0"], "--iterations: must be a positive integer; got 0"),
    (["--learning_rate=inf"], "--learning_rate: must be a positive finite number"),
    (["--weight_decay=-0.1"], "--weight_decay: must be a finite number ≥ 0; got -0.1"),
    (["--eval_every=0"], "--eval_every: must be a positive integer"),
    (["--capacity=0"], "--capacity: must be a positive integer"),
    (["--length_buckets=-1"], "--length_buckets: must be a positive integer"),
    (["--root_hidden=0"], "--root_hidden: must be a positive integer"),
    (["--strong_weight=-2"], "--strong_weight: must be a positive finite number"),
    (["--training=joint", "--root=mlp"], "--root: applies to level-wise training only; this run trains jointly "
                                          "(--training=joint): add --training=levelwise or drop --root"),
    (["--training=joint", "--anneal_temperature=0.5"], "--anneal_temperature: must be a finite number ≥ 1"),
    (["--training=levelwise", "--anneal_temperature=3"], "--anneal_temperature: applies to joint training only"),
    (["--split_rounds=-1"], "--split_rounds: must be a non-negative integer; got -1"),
    (["--segment_iterations=-5"], "--segment_iterations: must be a non-negative integer; got -5"),
    (["--iterations=100", "--segment_iterations=200"], "--segment_iterations: must be at most --iterations (100)"),
    (["--split_iterations=40", "--split_hint_iterations=50"],
     "--split_hint_iterations: must be at most --split_iterations (40); got 50"),
    (["--training=levelwise", "--split_rounds=2"], "--split_rounds: applies to joint training only"),
    (["--training=levelwise", "--segment_iterations=10"], "--segment_iterations: applies to joint training only"),
    (["--strong_warmup=100", "--anneal_temperature=2"],
     "--strong_warmup: applies to level-wise training only, and --anneal_temperature=2.0 to joint training only: "
     "drop one of them, or give --training"),
])
def test_bad_flags_are_refused_naming_the_flag(argv, message):
  with pytest.raises(config_flags.UsageError) as refused:
    config_flags.config_from_flags({}, _flags(*argv))
  assert str(refused.value).startswith(message), str(refused.value)


def test_a_level_wise_flag_beside_a_commands_joint_default_is_refused_naming_both():
  with pytest.raises(config_flags.UsageError, match=r"^--root: applies to level-wise training only, and memory gru "
                     r"\(this command's default here\) to joint training only: drop one of them, or give --training"):
    config_flags.config_from_flags({"memory": "gru"}, _flags("--root=mlp"))
  assert config_flags.config_from_flags({"memory": "gru"}, _flags("--root=mlp", "--memory=none")).root == "mlp"


def test_config_errors_name_the_field():
  for changes, field in [({"hidden": ()}, "hidden"), ({"capacity": 0}, "capacity"), ({"snapshot": "best"}, "snapshot"),
                         ({"seed": True}, "seed"), ({"min_capacity": (0, -1)}, "min_capacity"),
                         ({"call_graph": "some"}, "call_graph"), ({"segment_rule": "pairs"}, "segment_rule")]:
    with pytest.raises(config_lib.ConfigError) as refused:
      config_lib.TrainConfig(**changes)
    assert refused.value.field == field
  config = config_lib.TrainConfig(min_capacity=(0, 4))
  with pytest.raises(config_lib.ConfigError, match="min_capacity: needs one value per level") as refused:
    config_lib.check_levels(tasks.get("addition").spec, config)
  assert refused.value.field == "min_capacity"
  assert dataclasses.replace(config, min_capacity=(0, 4, 4)).min_capacity == (0, 4, 4)


def test_help_exits_0_and_shows_every_setting_grouped_with_its_default():
  proc = subprocess.run([sys.executable, "-m", "experiments.train", "--help"], capture_output=True, text=True,
                        timeout=120, cwd=ROOT)
  assert proc.returncode == 0, proc.stderr[-2000:]
  for field in config_lib.fields():
    assert f"--{field.name}:" in proc.stdout or f"--[no]{field.name}:" in proc.stdout, field.name
  text = " ".join(proc.stdout.split())  # the help is wrapped at 100 columns
  assert "Default: 2000 (bubblesort: 1000)" in text and "Default: the task's (addition: 160, fixed;" in text
  groups = [line for line in proc.stdout.splitlines() if line.endswith(":") and not line.startswith(" ")]
  assert groups == ["Flags of this command:", "Training settings:", "The run and its workdir:"]


def test_help_read_in_part_ends_quietly():
  proc = subprocess.Popen([sys.executable, "-m", "experiments.fit", "--help"], stdout=subprocess.PIPE,
                          stderr=subprocess.PIPE, cwd=ROOT)
  proc.stdout.close()  # as `... --help | head -1` does, but before the first line: the write always fails
  assert proc.wait(timeout=120) == 0 and proc.stderr.read() == b""


def test_a_seed_beyond_32_bits_is_refused():
  with pytest.raises(config_lib.ConfigError, match=r"seed: must be at most 2147483647 \(a 32-bit seed\)"):
    config_lib.TrainConfig(seed=2**31)
  with pytest.raises(config_lib.ConfigError, match=r"init_seed: must be at most 2147483647"):
    config_lib.TrainConfig(init_seed=2**31)


def test_init_seed_alone_sets_the_networks_initialisation():
  spec = tasks.get("nanocraft").spec
  params = lambda **kw: jax.tree.leaves(nnx.state(networks.make_hierarchy(spec, config_lib.TrainConfig(hidden=(4,),
                                                                                                    **kw))))
  restart, same_seed, other_seed = params(seed=1, init_seed=2), params(seed=2), params(seed=1)
  assert all(np.array_equal(a, b) for a, b in zip(restart, same_seed))
  assert not all(np.array_equal(a, b) for a, b in zip(restart, other_seed))
