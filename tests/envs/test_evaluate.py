"""`python -m experiments.evaluate`: good files solved by the oracle, malformed lines refused with exit 2."""
import json
import subprocess
import sys

import jax.numpy as jnp
import pytest
from flax import struct

from experiments.common import cli
from experiments.common import problems as problem_files
from php_jax.envs import addition, bubblesort_task, evaluation, nanocraft_task, tasks
from tests import processes


def _evaluate(tmp_path, task, lines):
  problems = tmp_path / "in.jsonl"
  problems.write_text("".join(line + "\n" for line in lines))
  out = tmp_path / "out.jsonl"
  proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", f"--task={task}", "--policy=oracle",
                         f"--problems={problems}", f"--out={out}"], capture_output=True, text=True,
                        timeout=300)
  return proc, out


def test_addition_file_solved_in_order(tmp_path):
  lines = ['{"a": "0123", "b": "4567"}', '{"a": "9999999999", "b": "0000000001"}', "",
           '{"a": "5", "b": "7"}', json.dumps({"a": "9" * 150, "b": "0" * 149 + "1"})]
  proc, out = _evaluate(tmp_path, "addition", lines)
  assert proc.returncode == 0, proc.stderr
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert [r["result"] for r in rows] == ["4690", "10000000000", "12", "1" + "0" * 150]
  assert rows[0] == {"result": "4690", "terminated": True, "valid": True, "steps": 23, "correct": True}
  assert all(r["terminated"] and r["valid"] and r["correct"] for r in rows)


def test_nanocraft_file_solved(tmp_path):
  lines = ['{"x": 1, "y": 2, "w": 3, "h": 2, "preplaced": [[2, 1], [3, 3]]}',
           '{"x": 4, "y": 4, "w": 2, "h": 2, "preplaced": []}']
  proc, out = _evaluate(tmp_path, "nanocraft", lines)
  assert proc.returncode == 0, proc.stderr
  rows = [json.loads(line) for line in out.read_text().splitlines()]
  assert len(rows) == 2 and all(r["correct"] for r in rows)
  assert rows[1]["grid"][4][4:] == [1, 1] and rows[1]["grid"][5][4:] == [1, 1]
  assert sum(map(sum, rows[1]["grid"])) == 4 and set(rows[0]) == {"grid", "terminated", "valid", "steps",
                                                                    "correct"}


def test_blank_file_is_refused(tmp_path):
  proc, out = _evaluate(tmp_path, "nanocraft", ["", "  "])
  assert proc.returncode == 2 and proc.stderr.strip() == f"error: no problems in {tmp_path / 'in.jsonl'}"
  assert not out.exists()


def test_bad_flags_are_refused_before_anything_runs(tmp_path):
  problems = tmp_path / "in.jsonl"
  problems.write_text('{"a": "1", "b": "2"}\n')
  (tmp_path / "adir").mkdir()
  cases = [(f"--out={problems}", "is the input file"), ("--batch_size=0", "batch_size"),
           ("--batch_size=x", "batch_size"), ("--tsk=addition", "tsk"),
           (f"--problems={tmp_path / 'adir'}", f"error: --problems={tmp_path / 'adir'}: Is a directory"),
           (f"--problems={tmp_path / 'none.jsonl'}", "none.jsonl: No such file or directory")]
  # Run at the same time, each with an --out of its own (which the first case's flag replaces).
  procs = processes.run_all([[sys.executable, "-m", "experiments.evaluate", "--task=addition", f"--problems={problems}",
                              f"--out={tmp_path / f'out{i}.jsonl'}", flag] for i, (flag, _) in enumerate(cases)],
                            capture_output=True, text=True, timeout=300)
  for (flag, message), proc in zip(cases, procs):
    assert proc.returncode == 2 and message in proc.stderr, (flag, proc.stderr)
    assert len(proc.stderr.strip().splitlines()) == 1, proc.stderr
  assert problems.read_text() == '{"a": "1", "b": "2"}\n' and sorted(p.name for p in tmp_path.iterdir()) == [
      "adir", "in.jsonl"]


def test_unusable_out_paths_are_refused(tmp_path):
  problems = tmp_path / "in.jsonl"
  problems.write_text("")
  (tmp_path / "link.jsonl").symlink_to(problems)
  (tmp_path / "hard.jsonl").hardlink_to(problems)
  inputs = {"problems": str(problems)}
  for out, message in [(tmp_path, "is a directory"), (tmp_path / "missing" / "out.jsonl", "does not exist"),
                       (problems, "is the input file --problems="), (tmp_path / "link.jsonl", "is the input file"),
                       (tmp_path / "hard.jsonl", "is the input file"), ("", "--out: must name a file")]:
    with pytest.raises(ValueError, match=message):
      cli.check_outputs({"out": str(out)}, inputs)
  cli.check_outputs({"out": str(tmp_path / "out.jsonl"), "log": None}, inputs)
  with pytest.raises(ValueError, match="--log=.*is the same file as --out="):
    cli.check_outputs({"out": str(tmp_path / "o.jsonl"), "log": str(tmp_path / "o.jsonl")}, inputs)
  (tmp_path / "run").mkdir()  # a --policy workdir's model files are inputs too
  with pytest.raises(ValueError, match=r"--out=.*run/model.json is the model file .*model.json of --policy=.*run$"):
    cli.check_outputs({"out": str(tmp_path / "run" / "model.json")}, {"policy": str(tmp_path / "run")})
  cli.check_outputs({"out": str(tmp_path / "run" / "decoded.jsonl")}, {"policy": str(tmp_path / "run")})
  with pytest.raises(ValueError, match=r"--out=.*run/results.json is the run's file .*results.json of --policy="):
    cli.check_outputs({"out": str(tmp_path / "run" / "results.json")}, {"policy": str(tmp_path / "run")})
  (tmp_path / "set.shards").mkdir()  # a demonstration set is a folder: nothing may be written inside it
  with pytest.raises(ValueError, match=r"--out=.*set.shards/o.jsonl is inside --demos=.*set.shards$"):
    cli.check_outputs({"out": str(tmp_path / "set.shards" / "o.jsonl")}, {"demos": str(tmp_path / "set.shards")})
  with pytest.raises(ValueError, match=r"--hierarchy_out=.*new.shards/h.json is inside --out=.*new.shards$"):
    cli.check_outputs({"out": str(tmp_path / "new.shards"), "hierarchy_out": str(tmp_path / "new.shards" / "h.json")},
                      {}, demo_sets=True, make_folders=True)
  for folder in ("model", "checkpoint", "candidates"):  # the run's own folders: a file there spoils it
    (tmp_path / "run" / folder).mkdir()
    with pytest.raises(ValueError, match=rf"--out=.*run/{folder}/x.jsonl is inside {folder}/ of --policy=.*run, "
                                         "which its run wrote: write elsewhere"):
      cli.check_outputs({"out": str(tmp_path / "run" / folder / "x.jsonl")}, {"policy": str(tmp_path / "run")})


def test_evaluate_refuses_to_write_over_the_model_it_reads(tmp_path):
  (tmp_path / "run").mkdir()
  problems = tmp_path / "in.jsonl"
  problems.write_text('{"a": "1", "b": "2"}\n')
  proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--task=addition",
                         f"--policy={tmp_path / 'run'}", f"--problems={problems}",
                         f"--out={tmp_path / 'run' / 'model.json'}"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 2 and proc.stderr.strip().endswith(f"is the model file {tmp_path / 'run' / 'model.json'} "
                                                               f"of --policy={tmp_path / 'run'}"), proc.stderr


def test_a_refusal_is_one_line_even_when_a_path_holds_a_newline(capsys):
  with pytest.raises(SystemExit) as ended:
    cli.fail("--out=a\nb: directory a\nb does not exist")
  assert ended.value.code == 2 and capsys.readouterr().err == "error: --out=a\\nb: directory a\\nb does not exist\n"


def test_malformed_line_exits_2_with_line_number_and_writes_nothing(tmp_path):
  proc, out = _evaluate(tmp_path, "addition", ['{"a": "12", "b": "34"}', '{"a": "12", "b": "3"}'])
  assert proc.returncode == 2
  assert "in.jsonl:2:" in proc.stderr and "same number of digits" in proc.stderr
  assert not out.exists()


def test_unknown_policy_exits_2(tmp_path):
  problems = tmp_path / "in.jsonl"
  problems.write_text('{"a": "1", "b": "2"}\n')
  proc = subprocess.run([sys.executable, "-m", "experiments.evaluate", "--task=addition",
                         f"--policy={tmp_path / 'nowhere'}", f"--problems={problems}",
                         f"--out={tmp_path / 'out.jsonl'}"], capture_output=True, text=True, timeout=300)
  assert proc.returncode == 2 and "no trained model in" in proc.stderr


_GOOD_LINES = {"addition": '{"a": "1", "b": "2"}', "nanocraft": '{"x": 1, "y": 1, "w": 2, "h": 2}',
               "bubblesort": '{"array": [2, 1]}'}


@pytest.mark.parametrize("task, line, message", [
    ("addition", '{"a": "12", "b": "3"}', "same number of digits"),
    ("addition", '{"a": "1x", "b": "23"}', "decimal digits"),
    ("addition", '{"a": "", "b": ""}', "decimal digits"),
    ("addition", '{"a": 12, "b": 34}', 'string fields "a" and "b"'),
    ("addition", '[1, 2]', "JSON object"),
    ("addition", '{"a": "1", "b": "2"', "Expecting"),
    ("nanocraft", '{"x": 0, "y": 1, "w": 2, "h": 2}', "does not fit"),
    ("nanocraft", '{"x": 3, "y": 1, "w": 4, "h": 2}', "does not fit"),
    ("nanocraft", '{"x": 1, "y": 1, "w": 3, "h": 3, "preplaced": [[2, 2]]}', "not on the building's perimeter"),
    ("nanocraft", '{"x": 1, "y": 1, "w": 3, "h": 3, "preplaced": [[9, 1]]}', "not on the building's perimeter"),
    ("nanocraft", '{"x": 1, "y": 1, "w": 2, "h": 2, "preplaced": [[1, 1], [1, 1]]}', "twice"),
    ("nanocraft", '{"x": 1, "y": 1, "w": 2, "h": 2, "preplaced": [[1]]}', "integer pairs"),
    ("nanocraft", '{"x": true, "y": 1, "w": 2, "h": 2}', "integer fields"),
    ("nanocraft", '{"x": 1, "y": 1, "w": 2, "h": 2, "preplace": [[1, 1]]}', "unknown key 'preplace'"),
    ("addition", '{"a": "1", "b": "2", "c": "3"}', "unknown key 'c'"),
    ("bubblesort", '{"arr": [2, 1]}', "unknown key 'arr'"),
    ("bubblesort", '{"array": [2, 1], "note": "x"}', "unknown key 'note'"),
    ("addition", b'{"a": "1", "b": "\xff"}', "not UTF-8"),
])
def test_parser_names_line_and_problem(tmp_path, task, line, message):
  path = tmp_path / "p.jsonl"
  path.write_bytes(_GOOD_LINES[task].encode() + b"\n" + (line if isinstance(line, bytes) else line.encode()) + b"\n")
  with pytest.raises(problem_files.ProblemFileError, match=message) as info:
    problem_files.read_problems(str(path), tasks.get(task))
  assert str(info.value).startswith(f"{path}:2:")


@struct.dataclass
class _Repeat:
  """A policy that takes one elementary action forever and never returns."""
  action: jnp.ndarray

  def operation(self, level, proc, tau, obs, key):
    return jnp.zeros(1, jnp.int32) if level < 2 else self.action

  def terminates(self, level, proc, tau, obs, key):
    return jnp.bool_(False)


def test_failed_episodes_say_why():
  task = tasks.get("addition")
  problems = [("12", "34"), ("5", "6")]
  off_the_tape = _Repeat(jnp.array([addition.MOVE, addition.IN1, addition.LEFT], jnp.int32))
  rows = evaluation.solve(task, off_the_tape, problems)  # width 8: the 8th move leaves the tape
  assert [r["failure"] for r in rows] == ["invalid action MOVE in1 LEFT at step 8"] * 2
  assert rows[0]["valid"] is False and list(rows[0])[-1] == "failure"
  writer = _Repeat(jnp.array([addition.WRITE, addition.OUT, 7], jnp.int32))
  budget = 2 * task.step_budget(8)
  assert [r["failure"] for r in evaluation.solve(task, writer, problems)] == [
      f"step budget exhausted after {budget} steps"] * 2
  assert all("failure" not in r for r in evaluation.solve(task, task.oracle, problems))


def test_actions_have_readable_names():
  assert tasks.get("addition").action_name([addition.WRITE, addition.OUT, 7]) == "WRITE out 7"
  assert tasks.get("addition").action_name([addition.MOVE, addition.IN1, addition.RIGHT]) == "MOVE in1 RIGHT"
  assert tasks.get("addition").action_name([0, 1, 5]) == "[0, 1, 5]"
  assert nanocraft_task.action_name([4]) == "PLACE_BLOCK"
  assert bubblesort_task.action_name([1, 0, 0]) == "SWAP i LEFT"
  assert bubblesort_task.action_name([0, 2, 1]) == "MOVE e RIGHT"
