"""The file readers refuse, never crash: arbitrary bytes and arbitrary JSON written to a demonstration file, a
hierarchy file or a problem file (each registered task) end in the reader's one-line error naming the path,
and each bound of php_jax.data.json_lines and of the readers has its explicit case."""
import io
import json
import pathlib
import re
import sys

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from experiments.common import problems as problem_files
from php_jax.data import demo_files, json_lines
from php_jax.demos import OBSERVATION_DTYPES
from php_jax.envs import tasks
from php_jax.hierarchy import HierarchySpec
from tests import processes

WAREHOUSE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "warehouse"
SPEC = HierarchySpec("t", (("r",), ("a", "b"), ("x", "y", "z")), (3, 2), 0)
GOOD_STACK = [[[0, 0], [0, 0], [1, 0]], [[0, 0], [0, 1], [2, 0]]]
GOOD = {"observations": [[0.0], [1.0], [2.0]], "actions": [[1, 0], [2, 1]], "stack": GOOD_STACK}
DEEP = "[" * 200_000 + "]" * 200_000
EXAMPLES = settings(max_examples=50, deadline=None, suppress_health_check=[HealthCheck.too_slow])

HUGE = st.sampled_from([10**400, -10**400, 2**31, 2**40, 2**63, 2**64, -2**63 - 1, 4 * 10**38, 1e39, -1e39])
SCALARS = st.none() | st.booleans() | st.integers() | st.floats() | st.text(max_size=6) | HUGE
JSON = st.recursive(SCALARS, lambda inner: st.lists(inner, max_size=4) | st.dictionaries(
    st.text(max_size=6), inner, max_size=4), max_leaves=16)
GOOD_LINES = [GOOD, {k: v for k, v in GOOD.items() if k != "stack"},
              {**GOOD, "stack": [None, [[0, 0], None, [-1, -1]]]},
              {"observations": [[0.5], [-3]], "actions": [[2, 1]], "stack": [[[0, 0], [1, 0], [2, 0]]]}]
GOOD_HIERARCHY = {"levels": [["r"], ["a", "b"], ["x"]], "action_sizes": [4, 2], "name": "h", "capacity": [None, 4, 2],
                  "hidden": [16, 8]}
GOOD_PROBLEMS = {"addition": {"a": "0123", "b": "4567"}, "bubblesort": {"array": [3, 1, 2]},
                 "nanocraft": {"x": 1, "y": 2, "w": 3, "h": 2, "preplaced": [[2, 1], [3, 3]]}}


@st.composite
def perturbed(draw, good: dict):
  """good with up to two of its parts, at any depth below the top, replaced by arbitrary JSON or numbers."""
  value = json.loads(json.dumps(good))
  for _ in range(draw(st.integers(0, 2))):
    _replace_part(draw, value)
  return value


def _replace_part(draw, value):
  key = draw(st.sampled_from(range(len(value)) if isinstance(value, list) else sorted(value)))
  if isinstance(value[key], (list, dict)) and value[key] and draw(st.integers(0, 3)):  # mostly deeper
    _replace_part(draw, value[key])
  else:
    value[key] = draw(JSON | HUGE | st.integers() | st.floats())


@pytest.fixture(scope="module")
def directory(tmp_path_factory):
  return tmp_path_factory.mktemp("files")


def _write(path, content) -> str:
  path.write_bytes(content if isinstance(content, bytes) else content.encode())
  return str(path)


def _lines(values) -> bytes:
  return b"".join((v if isinstance(v, bytes) else json.dumps(v).encode()) + b"\n" for v in values)


def _read_or_refuse(read, path: str, error: type[ValueError]):
  """read()'s result, or None when it raised error with one line that starts with the path."""
  try:
    return read()
  except error as e:
    message = str(e)
    assert len(message.splitlines()) == 1 and (message.startswith(path) or message == f"no problems in {path}"), (
        message)
    return None


def _demos(path: str):
  read = _read_or_refuse(lambda: demo_files.read_demonstrations(path, SPEC), path, demo_files.DemoFileError)
  if read is not None:
    batch, spec = read
    assert batch.observations.dtype.name in OBSERVATION_DTYPES and np.isfinite(batch.observations).all()
    assert ((0 <= batch.actions) & (batch.actions < np.array(SPEC.action_sizes))).all()
    assert (batch.counters < batch.observations.shape[1]).all() and spec.obs_dim > 0


def _hierarchy(path: str):
  read = _read_or_refuse(lambda: demo_files.read_hierarchy(path), path, demo_files.DemoFileError)
  if read is not None:
    sizes = read.spec.action_sizes + (read.hidden or ()) + tuple(c for c in read.capacity or () if c)
    assert all(1 <= n <= demo_files.MAX_SIZE for n in sizes)


def _problems(path: str, task: str):
  _read_or_refuse(lambda: problem_files.read_problems(path, tasks.get(task)), path,
                  problem_files.ProblemFileError)


def test_the_values_perturbed_below_are_read(directory):
  batch, _ = demo_files.read_demonstrations(_write(directory / "d.jsonl", _lines(GOOD_LINES)), SPEC)
  assert batch.strong.tolist() == [True, False, True, True]
  assert demo_files.read_hierarchy(_write(directory / "h.json", json.dumps(GOOD_HIERARCHY))).hidden == (16, 8)
  for task, problem in GOOD_PROBLEMS.items():
    assert len(problem_files.read_problems(_write(directory / "p.jsonl", _lines([problem])), tasks.get(task))) == 1


@EXAMPLES
@given(content=st.binary(max_size=200) | st.lists(st.binary(max_size=40) | JSON, max_size=3).map(_lines))
def test_arbitrary_bytes_are_refused_in_one_line(directory, content):
  _demos(_write(directory / "d.jsonl", content))
  _hierarchy(_write(directory / "h.json", content))
  for task in tasks.TASKS:
    _problems(_write(directory / "p.jsonl", content), task)


@EXAMPLES
@given(values=st.lists(JSON, min_size=1, max_size=3))
def test_arbitrary_json_is_refused_in_one_line(directory, values):
  _demos(_write(directory / "d.jsonl", _lines(values)))
  _hierarchy(_write(directory / "h.json", json.dumps(values[0])))
  for task in tasks.TASKS:
    _problems(_write(directory / "p.jsonl", _lines(values)), task)


@EXAMPLES
@given(lines=st.lists(st.sampled_from(GOOD_LINES).flatmap(perturbed), min_size=1, max_size=3))
def test_demonstration_like_lines_are_read_or_refused(directory, lines):
  _demos(_write(directory / "d.jsonl", _lines(lines)))


@EXAMPLES
@given(obj=perturbed(GOOD_HIERARCHY))
def test_hierarchy_like_files_are_read_or_refused(directory, obj):
  _hierarchy(_write(directory / "h.json", json.dumps(obj)))


@pytest.mark.parametrize("task", sorted(tasks.TASKS))
def test_problem_like_lines_are_read_or_refused(directory, task):
  @EXAMPLES
  @given(lines=st.lists(perturbed(GOOD_PROBLEMS[task]), min_size=1, max_size=3))
  def check(lines):
    _problems(_write(directory / "p.jsonl", _lines(lines)), task)
  check()


def _observations(value: str) -> str:
  return json.dumps(GOOD).replace("[[0.0], [1.0], [2.0]]", f"[[0.0], [{value}], [2.0]]")


def _stack_entry(entry: str) -> str:
  return json.dumps({**GOOD, "stack": [None, GOOD_STACK[1]]}).replace("[0, 1]", entry)


@pytest.mark.parametrize("line, message", [
    (_observations("1" + "0" * 400), "beyond ±3.4e38"),
    (_observations("1e39"), "number 1e39 is beyond ±3.4e38"),
    (_observations("-1e39"), "number -1e39 is beyond"),
    (_observations("1e400"), "number 1e400 is beyond"),
    (_observations("NaN"), "NaN is not a finite number"),
    (_observations("Infinity"), "Infinity is not a finite number"),
    (_observations("-Infinity"), "-Infinity is not a finite number"),
    (_observations("true"), "observation 1 must be a non-empty list of finite numbers"),
    (json.dumps({**GOOD, "observations": [[0.0, 1.0], [True, 1.0], [2.0, 1.0]]}), "observation 1 must be"),
    (_observations("null"), "observation 1 must be"),
    (_stack_entry("[1099511627776, 0]"), "procedure id 1099511627776 at level 1 is unknown"),
    (_stack_entry("[0, 1099511627776]"), "counter 1099511627776 is outside 0..1"),
    (_stack_entry("[0, 2147483647]"), "counter 2147483647 is outside 0..1"),
    (_stack_entry("[0, -1099511627776]"), "counter -1099511627776 is outside 0..1"),
    (_stack_entry("[true, 1]"), "expected [procedure, counter] or null; got [True, 1]"),
    (json.dumps({**GOOD, "stack": [None, [[0, 0], [0, 2], [2, 0]]]}),
     "stack step 1, level 1: counter 2 is outside 0..1"),
    (json.dumps({**GOOD, "actions": [[1, 0], [1099511627776, 0]]}),
     "action 1: factor 0 = 1099511627776 is outside 0..2"),
    (json.dumps({**GOOD, "actions": [[1, 0], [2**64, 0]]}), "factor 0 = 18446744073709551616 is outside"),
    (json.dumps({**GOOD, "actions": [[1, 0], [1, True]]}), "action 1 must be a list of 2 integers"),
    (json.dumps({**GOOD, "actions": [[1, 0], [1, 1.0]]}), "action 1 must be a list of 2 integers"),
    (json.dumps(GOOD)[:-1] + ', "actions": [[1, 0], [2, 1]]}', "key 'actions' appears twice"),
    (DEEP, "nested deeper than 32"),
    (_observations("[" * 100_000 + "]" * 100_000), "nested deeper than 32"),
    ('{"a":' * 100_000 + "1" + "}" * 100_000, "nested deeper than 32"),
])
def test_bad_numbers_and_structures_in_demonstrations(tmp_path, line, message):
  path = _write(tmp_path / "d.jsonl", json.dumps(GOOD) + "\n" + line + "\n")
  with pytest.raises(demo_files.DemoFileError, match=re.escape(message)) as error:
    demo_files.read_demonstrations(path, SPEC)
  assert str(error.value).startswith(f"{path}:2: malformed demonstration: ")


def test_a_json_syntax_error_is_placed_by_the_files_line_and_the_lines_column(tmp_path):
  good = json.dumps(GOOD)
  column = good.index(', "actions"') + 2  # where the comma was, counted from 1
  cases = [(good.replace(', "actions"', ' "actions"'), f"not JSON at column {column}: Expecting ',' delimiter"),
           (good[:-1], "not JSON, it ends too soon: Expecting ',' delimiter")]
  for line, message in cases:
    path = _write(tmp_path / "d.jsonl", good + "\n" + line + "\n" + good + "\n")
    with pytest.raises(demo_files.DemoFileError) as error:
      demo_files.read_demonstrations(path, SPEC)
    assert str(error.value) == f"{path}:2: malformed demonstration: {message}"
  path = _write(tmp_path / "h.json", '{"levels": [["r"], ["a"]],\n "action_sizes": [2],}')
  with pytest.raises(demo_files.DemoFileError) as error:
    demo_files.read_hierarchy(path)
  assert str(error.value) == (f"{path}: cannot read a hierarchy: not JSON at line 2, column 22: Expecting property "
                              "name enclosed in double quotes")


def test_an_integer_within_float32s_range_is_an_observation(tmp_path):
  line = _observations(str(3 * 10**38))
  batch, _ = demo_files.read_demonstrations(_write(tmp_path / "d.jsonl", line + "\n"), SPEC)
  assert batch.observations[0, 1, 0] == np.float32(3e38)


def _hierarchy_file(**keys) -> str:
  return json.dumps({"levels": [["r"], ["a", "b"], ["x"]], "action_sizes": [4], **keys})


@pytest.mark.parametrize("text, message", [
    (_hierarchy_file(action_sizes=[1099511627776]),
     '"action_sizes" must list positive integers .*got \\[1099511627776\\]'),
    (_hierarchy_file(action_sizes=[4097]), '"action_sizes" must list positive integers \\(at most 4096\\)'),
    (_hierarchy_file(action_sizes=[2] * 65), "action_sizes"),
    (_hierarchy_file(action_sizes=[True]), "action_sizes"),
    (_hierarchy_file(action_sizes=[-4]), "action_sizes"),
    (_hierarchy_file(capacity=[None, 1099511627776, 2]),
     '"capacity" must give one positive integer \\(at most 4096\\)'),
    (_hierarchy_file(capacity=[None, 0, 2]), "capacity"),
    (_hierarchy_file(hidden=[1099511627776]), '"hidden" must list positive layer sizes'),
    (_hierarchy_file(hidden=[8] * 65), "at most 64 layers"),
    (_hierarchy_file(hidden=[0]), "hidden"),
    (json.dumps({"levels": [["r"]] + [["p"]] * 64, "action_sizes": [2]}), "at most 64"),
    (json.dumps({"levels": [["r"], [f"p{i}" for i in range(4097)]], "action_sizes": [2]}), "at most 4096"),
    (_hierarchy_file()[:-1] + ', "hidden": [NaN]}', "cannot read a hierarchy: NaN is not a finite number"),
    (_hierarchy_file()[:-1] + ', "hidden": [1e39]}', "cannot read a hierarchy: number 1e39 is beyond"),
    (_hierarchy_file()[:-1] + ', "action_sizes": [4]}', "key 'action_sizes' appears twice"),
    (DEEP, "cannot read a hierarchy: arrays and objects nested deeper than 32"),
    (_hierarchy_file(observes=[None, {"a": [0]}]), '"observes" must give one object or null per level, root '
                                                   'first \\(3\\)'),
    (_hierarchy_file(observes=[None, {"c": [0]}, None]), '"observes": level 1 has no procedure \'c\''),
    (_hierarchy_file(observes=[None, {"a": [0, -1]}, None]), '"observes": \'a\' must list observation entries'),
    (_hierarchy_file(observes=[None, {"a": [True]}, None]), '"observes": \'a\' must list observation entries'),
    (_hierarchy_file(observes=[None, {"a": 3}, None]), '"observes": \'a\' must list observation entries'),
])
def test_bad_sizes_and_structures_in_hierarchy_files(tmp_path, text, message):
  path = _write(tmp_path / "h.json", text)
  with pytest.raises(demo_files.DemoFileError, match=message) as error:
    demo_files.read_hierarchy(path)
  assert str(error.value).startswith(f"{path}: ")


def test_observes_names_what_each_procedure_sees_and_must_fit_the_observations(tmp_path):
  path = _write(tmp_path / "h.json", _hierarchy_file(observes=[None, {"b": [2, 0, 2], "a": []}, {"x": [1]}]))
  spec = demo_files.read_hierarchy(path).spec
  assert spec.observes == (None, ((), (0, 2)), ((1,),))
  line = json.dumps({"observations": [[0, 0, 0]] * 2, "actions": [[1]]})
  _, read = demo_files.read_demonstrations(_write(tmp_path / "d.jsonl", line + "\n"), spec)
  assert read.obs_dim == 3 and read.observes == spec.observes
  nothing = _write(tmp_path / "nothing.json", _hierarchy_file(observes=[None, {}, None]))
  assert demo_files.read_hierarchy(nothing).spec.observes is None  # the same hierarchy as without the key
  narrow = _write(tmp_path / "narrow.jsonl", json.dumps({"observations": [[0, 0]] * 2, "actions": [[1]]}) + "\n")
  with pytest.raises(demo_files.DemoFileError, match="narrow.jsonl: the hierarchy does not fit these "
                     "demonstrations: observes: level 1's 'b' names observation entry 2, outside 0..1"):
    demo_files.read_demonstrations(narrow, spec)


@pytest.mark.parametrize("task, line, message", [
    ("addition", json.dumps({"a": "1" * 2**20, "b": "1" * 2**20}), "at most 1048574 digits"),
    ("addition", json.dumps({"a": "1x" * 100, "b": "1" * 200}), "decimal digits; got '1x1x1x"),
    ("addition", '{"a": "1", "b": "2", "a": "3"}', "key 'a' appears twice"),
    ("addition", '{"a": NaN, "b": "2"}', "NaN is not a finite number"),
    ("bubblesort", json.dumps({"array": [1] * 2**14}), "at most 16383"),
    ("bubblesort", '{"array": [1, 1099511627776]}', "entry 1 is 1099511627776"),
    ("bubblesort", '{"array": [1, -1]}', "entry 1 is -1"),
    ("bubblesort", '{"array": [1, 1' + "0" * 400 + "]}", "beyond ±3.4e38"),
    ("bubblesort", json.dumps({"array": [1, [0] * 10**5]}), "entry 1 is \\[0, 0, .*\\.\\.\\..* \\(300000 characters\\)$"),
    ("nanocraft", '{"x": 1e39, "y": 1, "w": 2, "h": 2}', "number 1e39 is beyond"),
    ("nanocraft", '{"x": 1099511627776, "y": 1, "w": 2, "h": 2}', "does not fit"),
    ("nanocraft", json.dumps({"x": 1, "y": 1, "w": 2, "h": 2, "preplaced": [[[0] * 10**5, 1]]}), "characters\\)$"),
    ("addition", DEEP, "nested deeper than 32"),
    ("bubblesort", DEEP, "nested deeper than 32"),
    ("nanocraft", DEEP, "nested deeper than 32"),
])
def test_bad_problem_lines_are_refused(tmp_path, task, line, message):
  path = _write(tmp_path / "p.jsonl", line + "\n")
  with pytest.raises(problem_files.ProblemFileError, match=message) as error:
    problem_files.read_problems(path, tasks.get(task))
  assert str(error.value).startswith(f"{path}:1: malformed {task} problem: ")


def test_long_lines_are_refused_at_their_number(tmp_path, monkeypatch):
  monkeypatch.setattr(json_lines, "MAX_LINE_BYTES", 200)
  assert list(json_lines.lines(io.BytesIO(b"a\n\n \n" + b"x" * 450 + b"\nb"))) == [
      (1, b"a\n"), (4, b"x" * 201), (5, b"b")]
  assert list(json_lines.lines(io.BytesIO(b" " * 400 + b"{}\n"))) == [(1, b" " * 201)]  # not taken for blank
  long = json.dumps({**GOOD, "observations": [[0.0], [1.0] * 40, [2.0]]})
  path = _write(tmp_path / "d.jsonl", json.dumps(GOOD) + "\n" + long + "\n")
  with pytest.raises(demo_files.DemoFileError, match=f"^{path}:2: malformed demonstration: longer than 200 bytes$"):
    demo_files.read_demonstrations(path, SPEC)
  path = _write(tmp_path / "p.jsonl", json.dumps({"a": "1" * 120, "b": "1" * 120}) + "\n")
  with pytest.raises(problem_files.ProblemFileError, match="p.jsonl:1: malformed addition problem: longer than"):
    problem_files.read_problems(path, tasks.get("addition"))
  path = _write(tmp_path / "h.json", _hierarchy_file(name="n" * 200))
  with pytest.raises(demo_files.DemoFileError, match="h.json: cannot read a hierarchy: longer than"):
    demo_files.read_hierarchy(path)


def test_depth_is_counted_outside_strings_only():
  brackets = "[" * 40
  obj = {"k": [brackets, "\\\"" + brackets, {"x": ['"]\\' + brackets]}]}
  assert json_lines.loads(json.dumps(obj).encode()) == obj
  deepest = []
  for _ in range(json_lines.MAX_DEPTH - 1):
    deepest = [deepest]
  assert json_lines.loads(json.dumps(deepest).encode()) == deepest
  with pytest.raises(json_lines.JSONBoundsError, match="nested deeper than 32"):
    json_lines.loads(json.dumps([deepest]).encode())


def test_commands_refuse_bad_numbers_in_one_line_before_writing(tmp_path):
  problems = _write(tmp_path / "p.jsonl", '{"a": "1", "b": "2"}\n' + DEEP + "\n")
  out = tmp_path / "out.jsonl"
  demos = _write(tmp_path / "d.jsonl", _observations("1e39") + "\n")
  workdir = tmp_path / "w"
  # The two commands at the same time.
  evaluate, fit = processes.run_all(
      [[sys.executable, "-m", "experiments.evaluate", "--task=addition", "--policy=oracle", f"--problems={problems}",
        f"--out={out}"],
       [sys.executable, "-m", "experiments.fit", f"--demos={demos}", f"--hierarchy={WAREHOUSE / 'warehouse.json'}",
        f"--workdir={workdir}"]], capture_output=True, text=True, timeout=300)
  assert evaluate.returncode == 2 and evaluate.stderr.strip() == (
      f"error: {problems}:2: malformed addition problem: arrays and objects nested deeper than 32")
  assert not out.exists()
  assert fit.returncode == 2 and fit.stderr.strip() == (
      f"error: {demos}:1: malformed demonstration: number 1e39 is beyond ±3.4e38 (float32's range)")
  assert not workdir.exists()
