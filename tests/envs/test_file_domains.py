"""examples/conveyor and examples/keypad: their generators write files that read back with stacks by the
call-stack rules, each domain has the call structure it is made to show, and the supervisor's stacks and
actions are a function of the recorded observations."""
import json
import pathlib

import numpy as np
import pytest

from examples.conveyor import make_files as conveyor
from examples.keypad import make_files as keypad
from php_jax.data import demo_files

EXAMPLES = pathlib.Path(__file__).resolve().parents[2] / "examples"
DOMAINS = [(conveyor, "conveyor"), (keypad, "keypad")]


def _make(module, name: str, out_dir: pathlib.Path, num_train=6, num_annotated=2, num_held_out=40, seed=3):
  """Runs a generator into out_dir; (hierarchy, train batch, held-out batch), every stack checked on reading."""
  module.main([f"--out_dir={out_dir}", f"--num_train={num_train}", f"--num_annotated={num_annotated}",
               f"--num_held_out={num_held_out}", f"--seed={seed}"])
  hierarchy = demo_files.read_hierarchy(str(out_dir / f"{name}.json"))
  train, _ = demo_files.read_demonstrations(str(out_dir / "train.jsonl"), hierarchy.spec)
  held_out, _ = demo_files.read_demonstrations(str(out_dir / "held_out.jsonl"), hierarchy.spec)
  return hierarchy, train, held_out


def _lowest_calls(demos) -> list[tuple[int, tuple[int, ...], np.ndarray]]:
  """(procedure, its actions, the observation before its first) of every lowest-level call of annotated demos."""
  calls = []
  for b, length in enumerate(np.asarray(demos.length)):
    for t in range(length):
      if demos.counters[b, t, -1] == 0:
        calls.append((int(demos.procedures[b, t, -1]), [], np.asarray(demos.observations[b, t])))
      calls[-1][1].append(int(demos.actions[b, t, 0]))
  return [(procedure, tuple(actions), o) for procedure, actions, o in calls]


@pytest.mark.parametrize("module,name", DOMAINS)
def test_the_files_read_back_as_the_committed_hierarchy_with_stacks_where_promised(module, name, tmp_path):
  hierarchy, train, held_out = _make(module, name, tmp_path)
  written, committed = (json.loads((folder / f"{name}.json").read_text()) for folder in (tmp_path, EXAMPLES / name))
  assert written == committed
  assert hierarchy.spec.num_levels == 3 and len(hierarchy.spec.levels[0]) == 1
  assert np.asarray(train.strong).tolist() == [True] * 2 + [False] * 4 and np.asarray(held_out.strong).all()
  lengths = np.concatenate([np.asarray(train.length), np.asarray(held_out.length)])
  assert lengths.min() >= 10 and lengths.max() <= 60


@pytest.mark.parametrize("module,name", DOMAINS)
def test_the_supervisor_replays_every_stack_and_action_from_the_observations_alone(module, name, tmp_path):
  _make(module, name, tmp_path)
  for file in ("train.jsonl", "held_out.jsonl"):
    for line in map(json.loads, (tmp_path / file).read_text().splitlines()):
      observations = np.asarray(line["observations"], np.float32)  # as the reader gives them
      stack, replayed = None, []
      for o in observations[:-1]:
        stack, action = module.supervisor_step(stack, o)
        replayed.append((stack, action))
      assert module.supervisor_step(stack, observations[-1]) is None  # the root returns after the last action
      assert [action for _, action in replayed] == line["actions"]
      if "stack" in line:
        assert [stack for stack, _ in replayed] == line["stack"]


@pytest.mark.parametrize("module,name", DOMAINS)
def test_training_and_held_out_demonstrations_come_from_disjoint_seeds(module, name, tmp_path):
  _make(module, name, tmp_path / "a", num_train=2, num_annotated=0)
  _make(module, name, tmp_path / "b", num_train=5, num_annotated=0)
  _make(module, name, tmp_path / "c", num_train=5, num_annotated=0, seed=4)
  held_out = [(tmp_path / run / "held_out.jsonl").read_text() for run in "abc"]
  assert held_out[0] == held_out[1] != held_out[2]  # the training set's size does not draw from their seeds
  train = (tmp_path / "b" / "train.jsonl").read_text().splitlines()
  assert (tmp_path / "a" / "train.jsonl").read_text().splitlines() == train[:2]


def test_conveyor_advance_calls_vary_in_length_with_the_distance_beside_calls_of_one_action(tmp_path):
  hierarchy, _, held_out = _make(conveyor, "conveyor", tmp_path)
  names = hierarchy.spec.levels[2]
  lengths = {name: set() for name in names}
  for procedure, actions, o in _lowest_calls(held_out):
    lengths[names[procedure]].add(len(actions))
    if names[procedure] == "advance":
      assert set(actions) == {conveyor.FORWARD} and len(actions) == round(o[0] * conveyor.MAX_GAP)
  assert len(lengths["advance"]) >= 4
  assert all(lengths[name] == {1} for name in names if name != "advance")


def test_keypad_type_procedures_differ_only_in_their_first_action(tmp_path):
  hierarchy, _, held_out = _make(keypad, "keypad", tmp_path)
  names = hierarchy.spec.levels[2]
  taken = {}
  for procedure, actions, _ in _lowest_calls(held_out):
    taken.setdefault(names[procedure], set()).add(actions)
  types = [f"type_{k}" for k in range(keypad.NUM_KEYS)]
  assert set(taken) == set(names) and all(len(taken[name]) == 1 for name in names)
  sequences = [next(iter(taken[name])) for name in types]
  assert {actions[1:] for actions in sequences} == {(keypad.ENTER, keypad.WAIT)}  # the same after the first
  assert [actions[0] for actions in sequences] == list(range(keypad.NUM_KEYS))  # whose keys all differ
  assert taken["press_open"] == {(keypad.OPEN,)} and taken["press_lock"] == {(keypad.LOCK,)}
