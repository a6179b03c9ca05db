"""The CompILE peer's reading of segments on hand-made cases (no torch needed), its loading of CompILE's code
from a checkout or a git directory (with stand-in files), and, where torch and a copy of CompILE are at hand
(COMPILE_DIR), a tiny run of the command. (The metrics themselves: tests/data/test_agreement.py.)"""
import json
import os
import subprocess
import sys

import numpy as np
import pytest

from experiments import compile_peer as peer


def test_segments_from_compile_boundaries():
  # Segment i covers [previous boundary, boundary i); boundaries made non-decreasing and at most T, the last T.
  assert peer.segments_from_boundaries([3, 2, 5, 9], 7).tolist() == [0, 0, 0, 2, 2, 3, 3]
  assert peer.segments_from_boundaries([2, 4, 0], 6).tolist() == [0, 0, 1, 1, 2, 2]
  segments = peer.segments_from_boundaries([1, 3, 3, 5], 5)  # segment 2 is empty
  assert segments.tolist() == [0, 1, 1, 3, 3]
  assert peer.boundary_steps(np.diff(segments, prepend=-1) != 0) == {1, 3}


def test_kmeans_and_action_symbols():
  points = np.concatenate([np.zeros((5, 2)), np.full((4, 2), 10.0)]) + np.arange(9)[:, None] * 0.01
  labels = peer.kmeans(points, 2, seed=3)
  assert len(set(labels[:5])) == len(set(labels[5:])) == 1 and labels[0] != labels[5]
  assert peer.kmeans(points[:1], 4, seed=0).tolist() == [0]
  assert peer.action_symbols([[0], [4], [2]], (5,)).tolist() == [1, 5, 3]
  assert peer.action_symbols([[0, 0], [1, 2], [0, 2]], (2, 3)).tolist() == [1, 6, 3]


STAND_IN = {"utils.py": "def get_losses(*a, **k):\n  return 'losses'\n\n"
                        "def get_reconstruction_accuracy(*a, **k):\n  return 'accuracy'\n",
            "modules.py": "import utils\n\nclass CompILE:\n  losses = utils.get_losses()\n"}


def test_load_compile_from_a_checkout_or_a_git_directory(tmp_path):
  checkout = tmp_path / "compile"
  checkout.mkdir()
  for name, text in STAND_IN.items():
    (checkout / name).write_text(text)
  before = sys.modules.get("utils")
  modules, utils, commit = peer.load_compile(str(checkout))
  assert modules.CompILE.losses == "losses" and utils.get_reconstruction_accuracy() == "accuracy"
  assert commit is None and sys.modules.get("utils") is before
  git = ["git", "-C", str(checkout), "-c", "user.name=t", "-c", "user.email=t@t"]
  for args in (["init", "-q"], ["add", "."], ["commit", "-q", "-m", "stand-in"]):
    subprocess.run(git + args, check=True, capture_output=True)
  head = subprocess.run(git + ["rev-parse", "HEAD"], capture_output=True, text=True, check=True).stdout.strip()
  assert peer.load_compile(str(checkout))[2] == head
  modules, _, commit = peer.load_compile(str(checkout / ".git"))
  assert commit == head and modules.CompILE.losses == "losses"
  with pytest.raises(ValueError, match="neither a checkout holding modules.py nor a git directory"):
    peer.load_compile(str(tmp_path))


@pytest.mark.slow
def test_command_runs_compile_on_a_tiny_file(tmp_path):
  """A few iterations of the real CompILE (COMPILE_DIR: a checkout or git directory of tkipf/compile)."""
  pytest.importorskip("torch")
  compile_dir = os.environ.get("COMPILE_DIR")
  if not compile_dir:
    pytest.skip("COMPILE_DIR (a copy of github.com/tkipf/compile) not set")
  (tmp_path / "h.json").write_text(json.dumps({"levels": [["r"], ["a", "b"], ["x", "y"]], "action_sizes": [2]}))
  lines = []
  for n_a, n_b in ((2, 3), (3, 2), (1, 4), (4, 1)):
    actions = [[0]] * n_a + [[1]] * n_b
    stack = [[[0, 0], [0, t], [0, 0]] for t in range(n_a)] + [[[0, 1], [1, t], [1, 0]] for t in range(n_b)]
    lines.append({"observations": [[0.0]] * (len(actions) + 1), "actions": actions, "stack": stack})
  (tmp_path / "d.jsonl").write_text("".join(json.dumps(line) + "\n" for line in lines))
  out = tmp_path / "out.json"
  proc = subprocess.run([sys.executable, "-m", "experiments.compile_peer", f"--compile_dir={compile_dir}",
                         f"--hierarchy={tmp_path / 'h.json'}", f"--demos={tmp_path / 'd.jsonl'}",
                         f"--held_out={tmp_path / 'd.jsonl'}", f"--out={out}", "--iterations=3", "--log_every=0"],
                        capture_output=True, text=True, timeout=300)
  assert proc.returncode == 0, proc.stderr
  row = json.loads(out.read_text())
  assert row == json.loads(proc.stdout.strip().splitlines()[-1])
  assert row["held_out_scored"] == 4 and row["true_boundaries"] == 4 and row["num_segments"] == 2
  for key in ("boundary_f1", "boundary_f1_within_1", "accuracy_up_to_renaming", "position_accuracy_up_to_renaming"):
    assert 0.0 <= row[key] <= 1.0
