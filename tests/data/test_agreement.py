"""Agreement measures on hand-made cases: call boundaries found (precision, recall, F1), the best renaming
(the Hungarian algorithm against brute force), labels and decoded frames under it."""
import itertools

import numpy as np
import pytest

from php_jax.data import agreement
from php_jax.demos import UNKNOWN


def _brute_force_assignment(score) -> list[tuple[int, int]]:
  """The best assignment by trying every injection of the smaller side into the larger."""
  score = np.asarray(score, np.float64)
  rows, cols = score.shape
  if rows <= cols:
    best = max(itertools.permutations(range(cols), rows), key=lambda p: score[np.arange(rows), list(p)].sum())
    return list(enumerate(best))
  best = max(itertools.permutations(range(rows), cols), key=lambda p: score[list(p), np.arange(cols)].sum())
  return sorted((r, c) for c, r in enumerate(best))


def _stack(frames):
  """[[(h, τ) per level, root first] per step] → (procedures, counters) [T, d]."""
  array = np.array(frames)
  return array[..., 0], array[..., 1]


# NanoCraft-like: root calls p0 (two one-step operations), then p1, whose first operation takes two steps
# (its counter stays 0), then p1 again (a new call of the same procedure: the root resumed).
STACK = _stack([[(0, 0), (0, 0), (0, 0)], [(0, 0), (0, 1), (0, 0)],
                [(0, 1), (1, 0), (1, 0)], [(0, 1), (1, 0), (1, 1)], [(0, 1), (1, 1), (2, 0)],
                [(0, 2), (1, 0), (2, 0)]])


def test_call_starts_follow_the_levels_above():
  assert agreement.call_starts(*STACK, level=1).tolist() == [True, False, True, False, False, True]
  # Level 2: a new call wherever a level above moved (step 3: level 2 resumed, no new call).
  assert agreement.call_starts(*STACK, level=2).tolist() == [True, True, True, False, True, True]
  assert agreement.boundary_steps(agreement.call_starts(*STACK, level=1)) == {2, 5}
  assert agreement.call_starts(np.zeros((0, 3), int), np.zeros((0, 3), int), 1).tolist() == []


def test_call_starts_refuse_unknown_frames_and_bad_levels():
  procs, taus = STACK[0].copy(), STACK[1].copy()
  procs[3, 0] = UNKNOWN
  with pytest.raises(ValueError, match="not known down to level 1"):
    agreement.call_starts(procs, taus, 1)
  procs[3, 0], procs[3, 2] = 0, UNKNOWN  # unknown below the level scored: fine
  assert agreement.call_starts(procs, taus, 1).tolist() == [True, False, True, False, False, True]
  with pytest.raises(ValueError, match="1 <= level < d"):
    agreement.call_starts(*STACK, level=3)


def test_boundary_scores_exact_and_within_a_step():
  truth, predicted = [{2, 5}, {3}], [{3, 5, 6}, {3}]
  exact = agreement.boundary_scores(truth, predicted)
  assert (exact["hits"], exact["true"], exact["predicted"]) == (2, 3, 4)
  assert exact["precision"] == pytest.approx(0.5) and exact["recall"] == pytest.approx(2 / 3)
  assert exact["f1"] == pytest.approx(2 * 0.5 * (2 / 3) / (0.5 + 2 / 3))
  near = agreement.boundary_scores(truth, predicted, tolerance=1)  # 3 hits 2, 5 hits 5; 6 has no partner left
  assert (near["hits"], near["precision"], near["recall"]) == (3, 0.75, 1.0)
  # Each true boundary is matched once, and the most hits are found: 4 → 3 and 6 → 5, not 4 → 5.
  assert agreement.boundary_scores([{3, 5}], [{4, 6}], tolerance=1)["hits"] == 2
  assert agreement.boundary_scores([{3, 5}], [{4}], tolerance=1)["hits"] == 1


def test_boundary_scores_empty_conventions():
  assert agreement.boundary_scores([set()], [set()]) == {"precision": 1.0, "recall": 1.0, "f1": 1.0, "hits": 0,
                                                     "true": 0, "predicted": 0}
  nothing = agreement.boundary_scores([{2}], [set()])
  assert (nothing["precision"], nothing["recall"], nothing["f1"]) == (1.0, 0.0, 0.0)
  with pytest.raises(ValueError, match="1 true and 2 predicted"):
    agreement.boundary_scores([{1}], [{1}, {2}])


def test_best_assignment_matches_brute_force():
  rng = np.random.default_rng(0)
  for _ in range(200):
    score = rng.integers(0, 10, rng.integers(1, 6, 2))
    found, best = agreement.best_assignment(score), _brute_force_assignment(score)
    assert len(found) == min(score.shape)
    assert len({r for r, _ in found}) == len({c for _, c in found}) == len(found)
    assert sum(score[r, c] for r, c in found) == sum(score[r, c] for r, c in best)
  assert agreement.best_assignment(np.zeros((0, 3))) == []
  assert agreement.best_assignment([[1, 5], [4, 1], [0, 0]]) == [(0, 1), (1, 0)]


def test_label_agreement_under_the_best_renaming():
  truth = [0, 0, 0, 1, 1, 2, 2, 2]
  assert agreement.label_agreement(truth, [7, 7, 7, 3, 3, 9, 9, 9]) == (1.0, {3: 1, 7: 0, 9: 2})
  # Two predicted labels cannot both be renamed 0: one of them counts as wrong.
  accuracy, renaming = agreement.label_agreement(truth, [4, 4, 5, 1, 1, 2, 2, 2])
  assert accuracy == pytest.approx(7 / 8) and renaming == {4: 0, 1: 1, 2: 2}
  # Fewer predicted labels than procedures: the unmatched procedure's steps are wrong.
  assert agreement.label_agreement(truth, [0, 0, 0, 0, 0, 1, 1, 1])[0] == pytest.approx(6 / 8)
  with pytest.raises(ValueError, match="equally many"):
    agreement.label_agreement([0, 1], [0])


def test_stack_boundary_scores_compare_decoded_calls_with_the_given_ones():
  procedures, counters = (np.stack([x, x]) for x in STACK)  # two demonstrations [2, T, 3]
  decoded_procedures, decoded_counters = procedures.copy(), counters.copy()
  decoded_counters[1, 4:, 0] = 1  # the second one's last call decoded as going on: its boundary at 5 missed
  scores = agreement.stack_boundary_scores(procedures, counters, decoded_procedures, decoded_counters, [6, 6], 1)
  assert (scores["hits"], scores["true"], scores["predicted"]) == (3, 4, 3)
  unknown = procedures.copy()
  unknown[0, 2, 1] = UNKNOWN  # not known down to level 1: left out
  scores = agreement.stack_boundary_scores(unknown, counters, decoded_procedures, decoded_counters, [6, 6], 1)
  assert (scores["hits"], scores["true"]) == (1, 2)
  unknown[1, 0, 0] = UNKNOWN
  assert agreement.stack_boundary_scores(unknown, counters, decoded_procedures, decoded_counters, [6, 6], 1) is None


@pytest.mark.parametrize("seed", range(5))
def test_procedures_alone_agree_at_least_as_often_as_frames_and_ignore_the_counters(seed):
  rng = np.random.default_rng(seed)
  procedures, counters = rng.integers(0, 3, (4, 7, 2)), rng.integers(0, 3, (4, 7, 2))
  decoded_procedures, decoded_counters = rng.integers(0, 4, (4, 7, 2)), rng.integers(0, 3, (4, 7, 2))
  procedures[0, 5:] = UNKNOWN  # padding
  _, frames = agreement.stack_agreement(procedures, counters, decoded_procedures, decoded_counters, 1)
  alone = agreement.stack_procedure_agreement(procedures, decoded_procedures, 1)
  assert frames <= alone + 1e-12
  renamed = (procedures[..., 1] + 1) % 3  # the same procedures under other names, counters shifted
  shifted = np.stack([procedures[..., 0], renamed], -1)
  assert agreement.stack_procedure_agreement(procedures, shifted, 1) == 1.0
  assert agreement.stack_agreement(procedures, counters, shifted, counters + 1, 1)[1] == 0.0
  assert agreement.stack_procedure_agreement(np.full((1, 3, 2), UNKNOWN), decoded_procedures[:1, :3], 1) is None
