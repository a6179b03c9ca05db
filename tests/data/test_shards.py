"""The binary demonstration format (php_jax.data.shards): the same arrays as the JSON lines it is written from,
and back; streaming shard by shard; each refusal in one line naming the file; writes whole or not at all; and
the commands that write, convert and read it."""
import dataclasses
import hashlib
import io
import json
import os
import re
import sys
import zipfile

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from php_jax.analysis import annotation_choice
from php_jax.data import demo_checks, demo_files, shards
from php_jax.demos import OBSERVATION_DTYPES, compact_dtype
from php_jax.envs import datasets, gym, tasks
from php_jax.hierarchy import HierarchySpec
from tests import processes
from tests.envs import test_gym

SPEC = HierarchySpec("t", (("r",), ("a", "b"), ("x", "y", "z")), (3, 2), 0)
STACK = [[[0, 0], [0, 0], [0, 0]], [[0, 0], [0, 0], [0, 1]], [[0, 0], [0, 1], [2, 0]], [[0, 1], [1, 0], [1, 0]]]
PARTLY = [None, [[0, 0], None, [1, 0]], [[0, 0], [-1, -1], [2, 0]], [[0, 1], [1, 0], None]]
LINES = [  # shard_size=2: a shard of uint8 observations, one of float16 (-0.0 included), one of float32
    {"observations": [[0, 1, 255, 7], [1, 0, 0, 0], [2, 0, 0, 1], [3, 3, 3, 3], [0, 0, 0, 0]],
     "actions": [[0, 0], [1, 1], [2, 0], [0, 1]], "stack": STACK},
    {"observations": [[1, 1, 1, 1], [0, 0, 0, 2]], "actions": [[2, 1]]},
    {"observations": [[0.5, -0.0, 1024, 3], [0.25, 1, 1, 1], [0, 0, 0, -2], [1, 1, 1, 1], [0, 0, 0, 0]],
     "actions": [[1, 0], [1, 0], [0, 0], [2, 1]], "stack": PARTLY},
    {"observations": [[0, 0, 0, 0], [0, 0, 0, 0], [1, 0, 0, 0]], "actions": [[0, 0], [0, 1]],
     "stack": [[[0, 0], [1, 0], [0, 0]], [[0, 0], [1, 1], [1, 0]]]},
    {"observations": [[0.1, 0, 0, 0], [0, 1e-30, 0, 0]], "actions": [[0, 1]], "stack": [None]}]


def _json_file(tmp_path, lines, name="d.jsonl") -> str:
  path = tmp_path / name
  path.write_text("".join(json.dumps(line) + "\n" for line in lines))
  return str(path)


def _assert_same(a, b):
  """Two batches hold the same arrays: dtypes, shapes and values (observations as float32 bit for bit, -0.0
  kept, in whatever type each holds them)."""
  for name, x, y in zip(a._fields, a, b):
    x, y = np.asarray(x), np.asarray(y)
    if name == "observations":
      x, y = (v.astype(np.float32).view(np.uint32) for v in (x, y))
    assert x.dtype == y.dtype and x.shape == y.shape, (name, x.dtype, y.dtype, x.shape, y.shape)
    assert np.array_equal(x, y), name


@pytest.fixture
def written(tmp_path):
  """(the JSON file, its batch, its binary copy in shards of 2)."""
  path = _json_file(tmp_path, LINES)
  batch, _ = demo_files.read_demonstrations(path, SPEC)
  out = str(tmp_path / "d.shards")
  demo_files.write_demonstrations(out, batch, batch.strong, shard_size=2)
  return path, batch, out


def _refusal(read, path: str) -> str:
  with pytest.raises(demo_checks.DemoFileError) as error:
    read()
  message = str(error.value)
  assert len(message.splitlines()) == 1 and message.startswith(path), message
  return message


def test_json_to_binary_to_json_reads_to_the_same_arrays(written, tmp_path):
  path, batch, out = written
  with open(os.path.join(out, shards.MANIFEST)) as f:
    manifest = json.load(f)
  assert [e["observations"] for e in manifest["shards"]] == ["uint8", "float16", "float32"]
  assert [e["demonstrations"] for e in manifest["shards"]] == [2, 2, 1] and manifest["observation_size"] == 4
  assert sorted(os.listdir(out)) == [shards.MANIFEST, "shard-00000.npz", "shard-00001.npz", "shard-00002.npz"]
  binary, spec = demo_files.read_demonstrations(out, SPEC)
  assert spec == demo_files.read_demonstrations(path, SPEC)[1] and spec.obs_dim == 4
  _assert_same(batch, binary)
  assert binary.observations.dtype == batch.observations.dtype == np.float32  # 0.1 is no float16
  assert np.asarray(binary.procedures)[2, 0].tolist() == [-1, -1, -1] and binary.strong.tolist() == [1, 0, 1, 1, 1]
  back = str(tmp_path / "back.jsonl")
  demo_files.write_demonstrations(back, binary, binary.strong)
  _assert_same(batch, demo_files.read_demonstrations(back, SPEC)[0])
  again = str(tmp_path / "again.shards")  # the same demonstrations write the same bytes
  demo_files.write_demonstrations(again, binary, binary.strong, shard_size=2)
  assert all(open(os.path.join(out, n), "rb").read() == open(os.path.join(again, n), "rb").read()
             for n in os.listdir(out))


def _file_bytes(path: str) -> dict[str, bytes]:
  """{name: bytes} of a set's files, or {"": bytes} of a file."""
  names = sorted(os.listdir(path)) if os.path.isdir(path) else [""]
  return {name: open(os.path.join(path, name) if name else path, "rb").read() for name in names}


def test_iter_demonstrations_converts_either_way_to_what_the_whole_read_writes(written, tmp_path):
  """Demonstrations read and written one at a time (as convert_demos does) give the bytes that reading the whole
  file and writing it gives, either way; a bad line met on the way leaves no output."""
  path, batch, out = written
  for source, target in ((out, "streamed.jsonl"), (path, "streamed.shards")):
    whole_target = str(tmp_path / f"whole_{target}")
    whole, _ = demo_files.read_demonstrations(source, SPEC)
    demo_files.write_demonstrations(whole_target, whole, whole.strong, shard_size=2)
    demo_files.write_unpadded(str(tmp_path / target), demo_files.iter_demonstrations(source, SPEC), shard_size=2)
    assert _file_bytes(str(tmp_path / target)) == _file_bytes(whole_target)
  bad = _json_file(tmp_path, [*LINES[:3], {"observations": [[0, 0, 0, 0]], "actions": [[9, 0]]}], "bad.jsonl")
  for target in ("out.jsonl", "out.shards"):
    with pytest.raises(demo_checks.DemoFileError, match="bad.jsonl:4: "):
      demo_files.write_unpadded(str(tmp_path / target), demo_files.iter_demonstrations(bad, SPEC), shard_size=2)
    assert not any(name.startswith((target, f".{target}")) for name in os.listdir(tmp_path))


def test_a_read_failing_mid_file_is_the_demonstrations_error_not_the_outputs(written, tmp_path, monkeypatch):
  """A disk error met while reading JSON lines (after some demonstrations were converted) names the file read,
  as a DemoFileError, and leaves no output; an error while writing stays an OSError for the writer to report."""
  path = written[0]

  def failing(lines):
    def read(f):
      for number, raw in lines(f):
        if number == 3:
          raise OSError(5, "Input/output error")
        yield number, raw
    return read
  monkeypatch.setattr(demo_files.json_lines, "lines", failing(demo_files.json_lines.lines))
  with pytest.raises(demo_checks.DemoFileError, match=f"^{re.escape(path)}: cannot read demonstrations: "
                     "Input/output error$"):
    demo_files.write_unpadded(str(tmp_path / "out.shards"), demo_files.iter_demonstrations(path, SPEC), shard_size=1)
  assert not any("out.shards" in name for name in os.listdir(tmp_path))
  with pytest.raises(demo_checks.DemoFileError, match=f"^{re.escape(path)}: cannot read demonstrations: "):
    demo_files.read_demonstrations(path, SPEC)
  monkeypatch.undo()

  def full_disk(*args, **kwargs):
    raise OSError(28, "No space left on device")
  monkeypatch.setattr(shards, "_write_new", full_disk)
  with pytest.raises(OSError, match="No space left") as raised:
    demo_files.write_unpadded(str(tmp_path / "out.shards"), demo_files.iter_demonstrations(path, SPEC), shard_size=1)
  assert not isinstance(raised.value, demo_checks.DemoFileError)


def _holds_each(dtype: np.dtype, values: np.ndarray) -> bool:
  """Whether every value, one at a time, comes back from dtype as the same float32 bits."""
  for x in values.ravel():
    if dtype.kind in "iu" and not (np.iinfo(dtype).min <= x <= np.iinfo(dtype).max and float(x).is_integer()):
      return False
    with np.errstate(over="ignore"):
      if np.float32(dtype.type(x)).view(np.uint32) != x.view(np.uint32):
        return False
  return True


@settings(max_examples=200, deadline=None)
@given(st.lists(st.sampled_from([0, 1, 7, 255, 256, -1, -128, -129, 300, 65535, 65536, -32768, -32769, 0.5,
                                 -0.0, 1024.25, 2049, 1e-30, 0.1, 1e5]), min_size=1, max_size=12),
       st.integers(1, 3))
def test_compact_dtype_is_the_narrowest_that_holds_every_value(values, columns):
  observations = np.resize(np.array(values, np.float32), (max(1, len(values) // columns), columns))
  chosen = compact_dtype(observations)
  assert chosen.name in OBSERVATION_DTYPES and _holds_each(chosen, observations)
  narrower = OBSERVATION_DTYPES[:OBSERVATION_DTYPES.index(chosen.name)]
  assert not any(_holds_each(np.dtype(d), observations) for d in narrower)


def test_compact_dtype_reads_every_row_of_a_large_array():
  zeros = np.zeros((1 << 17, 2), np.float32)  # rows are checked a block at a time: the last block decides here
  assert compact_dtype(zeros) == np.uint8
  assert compact_dtype(np.concatenate([zeros, [[300, 0]]])) == np.uint16
  assert compact_dtype(np.concatenate([zeros, [[-1, 0]], [[0.5, 0]]])) == np.float16


@pytest.mark.parametrize("values, stored, read", [
    ([[[-1, 5]], [[3, 0]]], ["int8", "uint8"], np.int8),
    ([[[300, 0]], [[-2, 1]]], ["uint16", "int8"], np.int16),
    ([[[-300, 2]], [[0.5, 1]]], ["int16", "float16"], np.float16),
    ([[[70000, 0]], [[1, 1]]], ["float32", "uint8"], np.float32),
    ([[[255, 0]], [[256, 1]]], ["uint8", "uint16"], np.uint16)])
def test_each_shard_and_each_read_holds_observations_in_the_narrowest_exact_type(tmp_path, values, stored, read):
  spec = HierarchySpec("t", (("r",), ("x",)), (2,), 0)
  lines = [{"observations": obs * 2, "actions": [[0]]} for obs in values]
  path = _json_file(tmp_path, lines)
  batch, _ = demo_files.read_demonstrations(path, spec)
  out = str(tmp_path / "d.shards")
  demo_files.write_demonstrations(out, batch, batch.strong, shard_size=1)
  with open(os.path.join(out, shards.MANIFEST)) as f:
    assert [e["observations"] for e in json.load(f)["shards"]] == stored
  binary, _ = demo_files.read_demonstrations(out, spec)
  assert binary.observations.dtype == batch.observations.dtype == read
  _assert_same(batch, binary)
  assert np.array_equal(binary.observations, np.array([obs * 2 for obs in values], np.float32))


def test_a_version_1_set_reads_as_it_was_written(written):
  _, batch, out = written  # uint8, float16 and float32 shards: the encodings version 1 knew
  manifest_path = os.path.join(out, shards.MANIFEST)
  with open(manifest_path) as f:
    manifest = json.load(f)
  assert manifest["version"] == shards.VERSION == 2
  with open(manifest_path, "w") as f:
    json.dump({**manifest, "version": 1}, f)
  _assert_same(batch, demo_files.read_demonstrations(out, SPEC)[0])


def test_iter_shards_yields_the_whole_read_a_shard_at_a_time(written):
  _, batch, out = written
  parts = list(shards.iter_shards(out, SPEC))
  assert [len(p.length) for p in parts] == [2, 2, 1]
  first = 0
  for part in parts:
    width = part.actions.shape[1]
    assert width == int(np.max(part.length))  # each shard padded to its own longest
    whole = type(batch)(*(np.asarray(x)[first:first + len(part.length)] for x in batch))
    trimmed = whole._replace(observations=whole.observations[:, :width + 1], actions=whole.actions[:, :width],
                             procedures=whole.procedures[:, :width], counters=whole.counters[:, :width])
    _assert_same(trimmed, part)
    first += len(part.length)


def test_recorded_lines_write_either_format_to_the_same_arrays(tmp_path):
  lines = [dict(line, observations=[[float(x) for x in o] for o in line["observations"]]) for line in LINES]
  for name in ("r.jsonl", "r.shards"):
    gym.write_demonstrations(str(tmp_path / name), lines)
  _assert_same(*(demo_files.read_demonstrations(str(tmp_path / name), SPEC)[0] for name in ("r.jsonl", "r.shards")))


def _cut(shard):
  shard.write_bytes(shard.read_bytes()[:-10])


def _tamper(shard):
  data = bytearray(shard.read_bytes())
  data[len(data) // 2] ^= 1
  shard.write_bytes(bytes(data))


@pytest.mark.parametrize("damage, file, message", [
    (_cut, "shard-00001.npz", "bytes where the manifest says"),
    (_tamper, "shard-00001.npz", "its sha256 differs from the manifest's (the file was changed or cut short)"),
    (lambda shard: shard.unlink(), "shard-00001.npz", "missing (the manifest lists it)"),
    (lambda shard: shard.with_name("notes.txt").write_text("x"), "notes.txt", "not in the manifest"),
    (lambda shard: shard.with_name(shards.MANIFEST).write_text('{"format": "other"}'), shards.MANIFEST,
     "not a demonstration set's manifest: its \"format\" is not 'php_jax demonstration shards'"),
    (lambda shard: shard.with_name(shards.MANIFEST).write_text("{"), shards.MANIFEST,
     "not a demonstration set's manifest: not JSON"),
    (lambda shard: shard.with_name(shards.MANIFEST).unlink(), "", "a directory without manifest.json")])
def test_a_damaged_set_is_refused_in_one_line_naming_the_file(written, tmp_path, damage, file, message):
  _, _, out = written
  damage(tmp_path / "d.shards" / "shard-00001.npz")
  assert message in _refusal(lambda: demo_files.read_demonstrations(out, SPEC), os.path.join(out, file).rstrip("/"))
  assert not shards.is_set(out) or damage in (_cut, _tamper)  # is_set: a damaged shard is a set's, to replace


def test_a_damaged_shard_is_refused_when_its_turn_comes(written, tmp_path):
  _, _, out = written
  _tamper(tmp_path / "d.shards" / "shard-00002.npz")
  stream = shards.iter_shards(out, SPEC)
  assert len(next(stream).length) == 2 and len(next(stream).length) == 2
  _refusal(lambda: next(stream), os.path.join(out, "shard-00002.npz"))


@pytest.mark.parametrize("spec, file, message", [
    (HierarchySpec("t", SPEC.levels, (3, 2), 5), shards.MANIFEST, "observations have 4 numbers where the hierarchy's "
     "have 5"),
    (HierarchySpec("t", SPEC.levels, (3,), 0), "shard-00000.npz", "actions have 2 factors where the hierarchy's "
     "have 1"),
    (HierarchySpec("t", (("r",), ("a", "b")), (3, 2), 0), "shard-00000.npz", "stacks have 3 levels where the "
     "hierarchy has 2"),
    (HierarchySpec("t", SPEC.levels, (2, 2), 0), "shard-00000.npz", "demonstration 0: action 2: factor 0 = 2 is "
     "outside 0..1"),
    (HierarchySpec("t", (("r",), ("a", "b"), ("x", "y")), (3, 2), 0), "shard-00000.npz", "demonstration 0: stack "
     "step 2: procedure id 2 at level 2 is unknown")])
def test_a_set_of_another_hierarchy_is_refused_as_its_json_lines_are(written, spec, file, message):
  path, _, out = written
  refusal = _refusal(lambda: demo_files.read_demonstrations(out, spec), os.path.join(out, file))
  assert message in refusal
  if "demonstration" in message:  # the same words as the JSON reader's, for the same demonstration
    json_refusal = _refusal(lambda: demo_files.read_demonstrations(path, spec), path)
    assert json_refusal == f"{path}:1: malformed demonstration: {refusal.split('demonstration 0: ')[1]}"


def test_bad_stacks_and_actions_are_refused_naming_shard_and_demonstration(tmp_path):
  stack = np.array(STACK)
  good = (np.zeros((5, 4)), np.zeros((4, 2), np.int32), stack[..., 0], stack[..., 1])
  broken = stack[..., 1].copy()
  broken[1, 2] = 2  # level 2's counter jumps from 0 to 2
  bad_stack = [good] * 3 + [(*good[:3], broken)]
  bad_action = [good] * 2 + [(good[0], good[1] + 3, *good[2:]), good]
  for name, chunk, message in (("stack", bad_stack, "demonstration 3: stack step 1: level 2 goes from (procedure 0, "
                                "counter 0) to (procedure 0, counter 2)"),
                               ("action", bad_action, "demonstration 2: action 0: factor 0 = 3 is outside 0..2")):
    out = str(tmp_path / f"{name}.shards")
    shards.write_shards(out, chunk, shard_size=2)
    assert message in _refusal(lambda: shards.read_demonstrations(out, SPEC), os.path.join(out, "shard-00001.npz"))


def test_the_stack_screen_finds_every_stack_the_rules_refuse():
  task = tasks.get("nanocraft")
  batch = datasets.training_demos(task, 1, 16, 16)
  rng = np.random.default_rng(0)
  stacks, refused = [], []
  for b, n in enumerate(np.asarray(batch.length)):
    for _ in range(8):
      procs, taus = np.array(batch.procedures[b, :n]), np.array(batch.counters[b, :n])
      for _ in range(rng.integers(0, 3)):  # a few entries made unknown, half-known, shifted or out of range
        t, level = rng.integers(0, n), rng.integers(0, task.spec.num_levels)
        (procs, taus, procs, taus)[rng.integers(0, 4)][t, level] += rng.choice([-2, -1, 1, 5])
      stacks.append((procs, taus))
      try:
        demo_checks.check_stack(procs, taus, task.spec)
        refused.append(False)
      except ValueError:
        refused.append(True)
  lengths = np.array([len(p) for p, _ in stacks])
  suspects = shards._stack_suspects(np.concatenate([p for p, _ in stacks]), np.concatenate([t for _, t in stacks]),
                                    lengths, task.spec)
  assert 0.2 < np.mean(refused) < 0.8 and set(np.flatnonzero(refused)) == set(suspects)


class _Interrupted(KeyboardInterrupt):
  pass


def test_an_interrupted_write_leaves_nothing_and_a_replaced_set_whole(written, tmp_path, monkeypatch):
  _, batch, out = written
  before = {n: open(os.path.join(out, n), "rb").read() for n in os.listdir(out)}
  calls = []

  def archive(arrays):
    calls.append(1)
    if len(calls) == 2:
      raise _Interrupted
    return original(arrays)

  original = shards._archive
  monkeypatch.setattr(shards, "_archive", archive)
  for target in (str(tmp_path / "new.shards"), out):
    calls.clear()
    with pytest.raises(_Interrupted):
      demo_files.write_demonstrations(target, batch, batch.strong, shard_size=2)
  assert not os.path.exists(tmp_path / "new.shards")
  assert {n: open(os.path.join(out, n), "rb").read() for n in os.listdir(out)} == before
  assert sorted(os.listdir(tmp_path)) == ["d.jsonl", "d.shards"]  # no temporary directory left
  monkeypatch.setattr(shards, "_archive", original)
  demo_files.write_demonstrations(out, batch, np.zeros(5, bool), shard_size=5)  # replaced whole
  assert sorted(os.listdir(out)) == [shards.MANIFEST, "shard-00000.npz"] and sorted(os.listdir(tmp_path)) == [
      "d.jsonl", "d.shards"]
  os.makedirs(tmp_path / "other.shards")
  (tmp_path / "other.shards" / "mine.txt").write_text("keep")
  with pytest.raises(FileExistsError):
    demo_files.write_demonstrations(str(tmp_path / "other.shards"), batch, batch.strong)
  assert os.listdir(tmp_path / "other.shards") == ["mine.txt"]


SHARD_BYTES = settings(max_examples=30, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])


@SHARD_BYTES
@given(st.binary(max_size=300) | st.sampled_from(["zip", "npy", "arrays"]))
def test_any_bytes_as_a_shard_are_refused_not_crashed_on(written, content):
  """Bytes whose sha256 the manifest gives (someone rewrote both): random, a zip of no arrays, one .npy, or
  an archive of the wrong arrays."""
  _, _, out = written
  buffer = io.BytesIO()
  if content == "zip":
    zipfile.ZipFile(buffer, "w").close()
  elif content == "npy":
    np.save(buffer, np.zeros(3))
  elif content == "arrays":
    np.savez(buffer, observations=np.zeros((3, 4), np.uint8), actions=np.zeros((2, 2)), lengths=np.array([2]),
             annotated=np.array([False]), procedures=np.zeros((0, 0), np.int32), counters=np.zeros((0, 0)))
  data = buffer.getvalue() or content
  with open(os.path.join(out, shards.MANIFEST)) as f:
    manifest = json.load(f)
  manifest["shards"][0].update(bytes=len(data), sha256=hashlib.sha256(data).hexdigest())
  with open(os.path.join(out, shards.MANIFEST), "w") as f:
    json.dump(manifest, f)
  with open(os.path.join(out, "shard-00000.npz"), "wb") as f:
    f.write(data)
  assert "not a shard of this format" in _refusal(lambda: demo_files.read_demonstrations(out, SPEC),
                                                  os.path.join(out, "shard-00000.npz"))


def test_export_record_convert_and_suggest_end_to_end(tmp_path):
  task = tasks.get("nanocraft")
  demos, hierarchy = tmp_path / "nc.shards", tmp_path / "nc.json"
  demo_files.write_hierarchy(str(hierarchy), task.spec)
  bad = tmp_path / "bad.shards"
  bad.mkdir()
  (bad / shards.MANIFEST).write_text('{"format": "php_jax demonstration shards", "version": 3}')
  (tmp_path / "taken.shards").mkdir()
  (tmp_path / "taken.shards" / "mine.txt").write_text("keep")
  export, *refused = processes.run_all([[sys.executable, "-m", *args] for args in [
      ("experiments.export_demos", "--task=nanocraft", "--num_demos=6", "--num_strong=2", "--seed=1",
       f"--out={demos}"),
      ("experiments.convert_demos", f"--demos={bad}", f"--hierarchy={hierarchy}", f"--out={tmp_path / 'o.jsonl'}"),
      ("experiments.export_demos", "--task=nanocraft", "--num_demos=2", f"--out={tmp_path / 'taken.shards'}")]],
      capture_output=True, text=True, timeout=600)
  assert export.returncode == 0 and "6 training demonstrations (2 annotated)" in export.stdout, export.stderr
  assert [(proc.returncode, proc.stderr) for proc in refused] == [
      (2, f"error: {bad}/{shards.MANIFEST}: not a demonstration set's manifest: version 3; this php_jax reads "
       "versions 1 and 2\n"),
      (2, f"error: --out={tmp_path / 'taken.shards'}: something that is not a demonstration set is there; not "
       "replaced\n")]
  suggest, convert, record = processes.run_all([[sys.executable, "-m", *args] for args in [
      ("experiments.suggest", f"--demos={demos}", f"--hierarchy={hierarchy}", "--budget=2",
       f"--out={tmp_path / 's.jsonl'}"),
      ("experiments.convert_demos", f"--demos={demos}", f"--hierarchy={hierarchy}", f"--out={tmp_path / 'nc.jsonl'}"),
      ("experiments.record", "--env=tests.envs.test_gym:make_corridor", "--expert=tests.envs.test_gym:CorridorExpert",
       "--episodes=4", "--annotated=1", f"--out={tmp_path / 'corridor.shards'}")]],
      capture_output=True, text=True, timeout=600)
  assert suggest.returncode == 0 and convert.returncode == 0 and record.returncode == 0, (
      suggest.stderr, convert.stderr, record.stderr)
  lines = gym.record(test_gym.make_corridor(), test_gym.CorridorExpert(None), episodes=4, seed=0, annotate=1)
  gym.write_demonstrations(str(tmp_path / "corridor.jsonl"), lines)
  _assert_same(*(demo_files.read_demonstrations(str(tmp_path / name), test_gym.SPEC)[0]
                 for name in ("corridor.jsonl", "corridor.shards")))
  expected = datasets.problem_demonstrations(task, task.training_problems(1, 6), 0)
  annotated = datasets.strong_mask(6, 2, 1)
  spec = dataclasses.replace(task.spec, obs_dim=0)
  for path in (demos, tmp_path / "nc.jsonl"):
    read, _ = demo_files.read_demonstrations(str(path), spec)
    assert np.array_equal(read.strong, annotated) and np.array_equal(read.observations, expected.observations)
  chosen = annotation_choice.suggest(read, 2, task.action_name)
  with open(tmp_path / "s.jsonl") as f:
    assert [json.loads(line)["index"] for line in f] == [c.index for c in chosen]
  assert not [n for n in os.listdir(tmp_path) if n.startswith(".")] and not os.path.exists(tmp_path / "o.jsonl")
  assert os.listdir(tmp_path / "taken.shards") == ["mine.txt"]
