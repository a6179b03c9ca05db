"""The split search's moves keep the probability of every stack they relabel, its judge is the exact
likelihood, and its rounds are read off the most likely stacks."""
import jax
import numpy as np
import pytest
from flax import nnx

from php_jax.analysis import decoding
from php_jax.data import agreement
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.envs import datasets, tasks
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy
from php_jax.training import networks, objective, split_search
from php_jax.training.config import TrainConfig, resolved

NANOCRAFT = tasks.get("nanocraft")
CAPACITY = (8, 8, 8)


def _hierarchy(seed=1):
  return networks.make_hierarchy(NANOCRAFT.spec, TrainConfig(hidden=(8,), seed=seed))


def test_a_split_by_caller_moves_the_callers_stacks_to_the_copy_with_their_probabilities():
  one = jax.tree.map(lambda x: np.asarray(x)[:1], datasets.training_demos(NANOCRAFT, 1, 1, 1))
  caller, p = (int(x) for x in one.procedures[0, 0, 1:])
  q, r = [k for k in range(NANOCRAFT.spec.num_procs(2)) if k != p][:2]
  level2 = one.procedures[..., 2]  # a stack that leaves q unused: the supervisor's, with r for q
  one = one._replace(procedures=one.procedures.copy())
  one.procedures[..., 2] = np.where(level2 == q, r, level2)
  hierarchy = _hierarchy()
  before = objective.stack_log_likelihoods(hierarchy, one, CAPACITY)
  split_search.apply(hierarchy, split_search.Move("", 2, p, q, caller=caller), jax.random.key(0), noise=0.0)
  relabelled = one.procedures.copy()
  mine = (relabelled[..., 1] == caller) & (relabelled[..., 2] == p)
  relabelled[..., 2] = np.where(mine, q, relabelled[..., 2])
  assert mine.any() and not mine.all()
  after = objective.stack_log_likelihoods(hierarchy, one._replace(procedures=relabelled), CAPACITY)
  np.testing.assert_allclose(after, before, rtol=1e-5)
  # The other callers still call p: the annotated stack, where p runs for them, keeps its probability only if
  # the caller's calls were moved too; without relabelling, the caller now calls p as unlikely as it called q.
  unmoved = objective.stack_log_likelihoods(hierarchy, one, CAPACITY)
  assert float(unmoved[0]) < float(before[0]) - 1e-3


def test_a_copy_computes_what_its_source_computes():
  hierarchy = _hierarchy()
  split_search.apply(hierarchy, split_search.Move("", 1, 2, 4), jax.random.key(0), noise=0.0)
  php = hierarchy.levels[1]
  obs, tau = np.linspace(-1, 1, NANOCRAFT.spec.obs_dim, dtype=np.float32)[None], np.arange(3, dtype=np.float32)
  logits = php.termination_logits(obs, tau)
  np.testing.assert_allclose(logits[4], logits[2], rtol=1e-6)
  operations = php.op_log_probs(obs, tau)[0]
  np.testing.assert_allclose(operations[4], operations[2], rtol=1e-6)


def test_the_judge_is_the_exact_log_likelihood_per_step_of_every_candidate():
  judge = datasets.training_demos(NANOCRAFT, 3, 5, 5)  # annotated: the judge ignores annotations
  candidates = [_hierarchy(1), _hierarchy(2)]
  scores = split_search.judge_scores(candidates, CAPACITY, judge)
  for candidate, score in zip(candidates, scores):
    decoded = decoding.decode(candidate, CAPACITY, judge)
    np.testing.assert_allclose(score, decoding.log_likelihood_per_step(decoded.log_likelihood, judge.length)[0],
                               rtol=1e-5)


def test_candidate_moves_are_read_off_the_most_likely_stacks():
  demos = datasets.training_demos(NANOCRAFT, 1, 16, 0)
  hierarchy = _hierarchy()
  moves = split_search.candidate_moves(hierarchy, CAPACITY, demos)
  decoded = decoding.decode(hierarchy, CAPACITY, demos)
  stacks = split_search.most_likely_stacks(hierarchy, CAPACITY, demos)  # the search's own decoding
  np.testing.assert_array_equal(stacks.procedures, decoded.procedures)
  np.testing.assert_array_equal(stacks.counters, decoded.counters)
  by_caller = [m for m in moves if m.caller is not None]
  by_counter = [m for m in moves if m.hinted is not None]
  assert len(by_caller) + len(by_counter) == len(moves) and 0 < len(moves) <= 2 * split_search.MOVES_PER_KIND
  for move in by_caller:  # the caller really calls the source in some most likely stack
    calls = [(procs[starts, 1], procs[starts, 2]) for procs, starts in
             ((decoded.procedures[b, :n], agreement.call_starts(decoded.procedures[b, :n], decoded.counters[b, :n], 2))
              for b, n in enumerate(demos.length))]
    assert any(((c == move.caller) & (p == move.source)).any() for c, p in calls)
    assert move.copy != move.source
  for move in by_counter:  # the hint names the copy where the root calls the source at one counter
    hinted = move.hinted
    assert hinted.strong.all() and (hinted.counters == UNKNOWN).all()
    level1 = hinted.procedures[..., 1]
    assert (level1 == move.copy).any() and set(np.unique(level1)) <= set(np.unique(decoded.procedures[..., 1])) | {
        move.copy, UNKNOWN}
    assert (hinted.procedures[..., [0, 2]] == UNKNOWN).all()


@pytest.mark.slow
def test_a_round_keeps_the_best_judged_candidate_and_is_deterministic():
  demos = datasets.training_demos(NANOCRAFT, 1, 8, 0)
  config = resolved(TrainConfig(hidden=(8,), seed=1, split_iterations=3, split_hint_iterations=1), demos,
                          NANOCRAFT.spec)
  results = []
  for _ in range(2):
    kept, entry = split_search.search_round(_hierarchy(), CAPACITY, demos, demos, config, 0)
    results.append((kept, entry))
  (kept, entry), (again, entry_again) = results
  scores = [s for _, s in entry["candidates"]]
  assert entry["kept"] == entry["candidates"][int(np.argmax(scores))][0] and entry["candidates"][0][0] == "unchanged"
  assert entry == entry_again
  for a, b in zip(jax.tree.leaves(nnx.state(kept, nnx.Param)), jax.tree.leaves(nnx.state(again, nnx.Param))):
    np.testing.assert_array_equal(a, b)
  np.testing.assert_allclose(split_search.judge_scores([kept], CAPACITY, demos)[0],
                             entry["log_likelihood_per_step"], rtol=1e-6)


def test_a_level_with_one_caller_or_no_procedure_to_spare_gives_no_move():
  spec = HierarchySpec("one_caller", (("root",), ("only",), ("x", "y")), (3,), 2)
  hierarchy = PHPHierarchy(spec, hidden=(4,), rngs=nnx.Rngs(0))
  actions = np.array([[[0], [0], [1], [2], [2], [1]]], np.int32)
  unknown = np.full((1, 6, 3), UNKNOWN, np.int32)
  demos = Demonstration(np.zeros((1, 7, 2), np.float32), actions, unknown, unknown, np.array([6]), np.array([False]))
  assert split_search.candidate_moves(hierarchy, (8, 8, 8), demos) == []
