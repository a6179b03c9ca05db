"""The split search (`TrainConfig.split_rounds`): after joint training, a procedure that serves two roles is
given a copy for one of them, one move a round, kept only if the hierarchy then explains the judging
demonstrations better.

Training without annotation can merge two of the supervisor's procedures into one that two callers share, or
that the root calls at two of its counters. A round reads candidate moves off the most likely stacks of the
training demonstrations (`candidate_moves`): for each procedure p below level 1 that several procedures of
the level above call, its second-busiest caller calls a copy of p instead; for each level-1 procedure that
the root calls at several of its counters, the calls at the second-busiest counter go to a copy. The copy
takes the place of its level's least-used procedure, which gives up its calls. Every candidate and the
unchanged hierarchy train config.split_iterations more, as one vmapped program (a split by counter first
learns its relabelled procedures as a partial annotation: the root's networks cannot be changed for one
counter alone), and the round keeps the one with the highest log-likelihood per step on the judging
demonstrations. The search ends after config.split_rounds rounds, or once a round keeps the unchanged one.
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import fitting
from php_jax.data import agreement, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.inference import stack_lattice
from php_jax.model import PHPHierarchy
from php_jax.training import objective
from php_jax.training.config import TrainConfig

MOVES_PER_KIND = 3  # candidates of each kind a round tries, the busiest procedure's first
UNCHANGED = "unchanged"


class Move(NamedTuple):
  """One candidate: level `level`'s procedure `copy` becomes a copy of `source`, called by `caller` (of the
  level above) in place of source (a split by caller), or where `hinted` (the demonstrations with the
  relabelled level-1 procedures as a partial annotation) says (a split by the root's counter)."""
  description: str
  level: int
  source: int
  copy: int
  caller: int | None = None
  hinted: Demonstration | None = None


def candidate_moves(hierarchy: PHPHierarchy, capacity: tuple[int, ...], demos: Demonstration) -> list[Move]:
  """The moves the most likely stacks of demos suggest: up to MOVES_PER_KIND splits by caller at each level
  from 2 down, then up to MOVES_PER_KIND splits by the root's counter at level 1."""
  decoded = most_likely_stacks(hierarchy, capacity, demos)
  fits = np.isfinite(decoded.log_prob)  # the stacks of demonstrations that fit none are not read
  decoded = decoded._replace(procedures=np.where(fits[:, None, None], decoded.procedures, UNKNOWN),
                             counters=np.where(fits[:, None, None], decoded.counters, UNKNOWN))
  spec, lengths = hierarchy.spec, np.asarray(demos.length)
  stacks = [(decoded.procedures[b, :n], decoded.counters[b, :n]) for b, n in enumerate(lengths) if fits[b]]
  moves = []
  for level in range(2, spec.num_levels):
    if min(spec.num_procs(level - 1), spec.num_procs(level)) < 2:
      continue  # one caller, or no procedure to spare for the copy
    counts = np.zeros((spec.num_procs(level - 1), spec.num_procs(level)), int)  # [caller, callee] calls
    for procedures, counters in stacks:
      starts = agreement.call_starts(procedures, counters, level)
      np.add.at(counts, (procedures[starts, level - 1], procedures[starts, level]), 1)
    used = counts.sum(0)
    found = []
    for p in np.argsort(-used, kind="stable"):
      callers = np.argsort(-counts[:, p], kind="stable")
      if counts[callers[1], p] > 0:
        q = _least_used(used, p)
        found.append(Move(f"level {level}: {q} becomes a copy of {p} for caller {callers[1]}", level, int(p), q,
                          caller=int(callers[1])))
    moves += found[:MOVES_PER_KIND]
  return moves + _counter_moves(decoded, stacks, demos, spec.num_procs(1))[:MOVES_PER_KIND]


def _counter_moves(decoded: stack_lattice.StackPath, stacks: list, demos: Demonstration, num_procs: int) -> list[Move]:
  """Splits by the root's counter at level 1, each with its hinted demonstrations."""
  if num_procs < 2:
    return []
  counts = np.zeros((num_procs, decoded.counters.shape[1] + 1), int)  # [level-1 procedure, root counter] calls
  for procedures, counters in stacks:
    starts = agreement.call_starts(procedures, counters, 1)
    np.add.at(counts, (procedures[starts, 1], counters[starts, 0]), 1)
  used, moves = counts.sum(1), []
  level1, root_counter = decoded.procedures[..., 1], decoded.counters[..., 0]
  strong = np.asarray(demos.strong)
  counters = np.where(strong[:, None, None], np.asarray(demos.counters), UNKNOWN).astype(np.int32)
  for p in np.argsort(-used, kind="stable"):
    by_counter = np.argsort(-counts[p], kind="stable")
    if counts[p, by_counter[1]] > 0:
      q, tau = _least_used(used, p), int(by_counter[1])
      procedures = np.full(np.shape(demos.procedures), UNKNOWN, np.int32)
      procedures[..., 1] = np.where(level1 == q, UNKNOWN, np.where((level1 == p) & (root_counter == tau), q, level1))
      procedures[strong] = np.asarray(demos.procedures)[strong]
      hinted = demos._replace(procedures=procedures, counters=counters, strong=np.ones_like(strong))
      moves.append(Move(f"level 1: {q} becomes a copy of {p} for root counter {tau}", 1, int(p), q, hinted=hinted))
  return moves


def _least_used(used: np.ndarray, p: int) -> int:
  """The least-used procedure other than p (the first of equals)."""
  return int(min((c for c in range(len(used)) if c != p), key=lambda c: used[c]))


def apply(hierarchy: PHPHierarchy, move: Move, key: jax.Array, noise: float = 0.01) -> None:
  """Makes the move in place: move.copy's networks become move.source's, plus Gaussian noise of `noise` times
  each parameter array's spread; for a split by caller, the caller's logits of source and copy are swapped,
  so that it calls the copy as it called source, and every stack without the copy keeps its probability."""
  php = hierarchy.levels[move.level]
  for mlp in (php.operation, php.termination):
    for param in (*mlp.kernels, *mlp.biases):
      value = param[...]
      key, sub = jax.random.split(key)
      jitter = noise * jnp.std(value[move.source]) * jax.random.normal(sub, value[move.source].shape)
      param[...] = value.at[move.copy].set(value[move.source] + jitter)
  if move.caller is not None:
    head = hierarchy.levels[move.level - 1].operation
    c, p, q = move.caller, move.source, move.copy
    for param in (head.kernels[-1], head.biases[-1]):
      value = param[...]
      param[...] = value.at[c, ..., q].set(value[c, ..., p]).at[c, ..., p].set(value[c, ..., q])


def most_likely_stacks(hierarchy: PHPHierarchy, capacity: tuple[int, ...],
                       demos: Demonstration) -> stack_lattice.StackPath:
  """Each demonstration's most likely stack under the hierarchy: procedures, counters [B, T, d] numpy (root
  first; UNKNOWN on padding) and log_prob [B]."""
  return jax.device_get(objective.stack_query(hierarchy, capacity, stack_lattice.viterbi, demos.observations,
                                              demos.actions, demos.length))


def judge_scores(candidates: list[PHPHierarchy], capacity: tuple[int, ...],
                 demos: Demonstration) -> list[float]:
  """Per candidate, Σ log P(actions) / Σ length of demos (−inf if a demonstration fits no stack): one
  compiled program for every candidate of one architecture."""
  steps = float(np.sum(demos.length))
  return [float(np.sum(np.asarray(objective.stack_query(c, capacity, stack_lattice.log_likelihood, demos.observations,
                                                        demos.actions, demos.length), np.float64))) / steps
          for c in candidates]


def train_candidates(candidates: list[PHPHierarchy], first_data: list[Demonstration], demos: Demonstration,
                     capacity: tuple[int, ...], config: TrainConfig) -> None:
  """Trains every candidate config.split_iterations on demos as one vmapped program, candidate i's first
  config.split_hint_iterations on first_data[i] (demos, or its hinted demonstrations); in place."""
  def loss(hierarchy, buckets):
    return objective.stack_loss(hierarchy, buckets, capacity, config.strong_weight, call_penalty=config.call_penalty)

  def stacked(data: list[Demonstration]):
    return jax.tree.map(lambda *leaves: jnp.stack(leaves),
                        *[views.demonstration_buckets(d, config.length_buckets) for d in data])

  hooks, progress = fitting.Hooks(log=lambda s, row: None), None
  if any(d is not demos for d in first_data) and config.split_hint_iterations:
    progress = fitting.fit_seeds(candidates, loss, _schedule(config, config.split_hint_iterations), hooks,
                                 args=(stacked(first_data),))
  fitting.fit_seeds(candidates, loss, _schedule(config, config.split_iterations), hooks, progress,
                    args=(stacked([demos] * len(candidates)),))


def _schedule(config: TrainConfig, iterations: int) -> fitting.Schedule:
  return fitting.Schedule(iterations, config.learning_rate, max(iterations, 1), weight_decay=config.weight_decay)


def search_round(hierarchy: PHPHierarchy, capacity: tuple[int, ...], demos: Demonstration, judge: Demonstration,
                 config: TrainConfig, round_index: int) -> tuple[PHPHierarchy, dict]:
  """One round from hierarchy: (the kept hierarchy, the round's log entry {"round", "kept",
  "log_likelihood_per_step", "candidates": [[description, log-likelihood per step], ...]}; a log-likelihood
  of None where some judging demonstration fits no stack)."""
  moves = candidate_moves(hierarchy, capacity, demos)
  keys = jax.random.split(jax.random.fold_in(jax.random.key(config.network_seed), round_index), max(len(moves), 1))
  candidates = [nnx.clone(hierarchy) for _ in range(len(moves) + 1)]
  for candidate, move, key in zip(candidates[1:], moves, keys):
    apply(candidate, move, key)
  train_candidates(candidates, [demos] + [demos if m.hinted is None else m.hinted for m in moves], demos, capacity,
                   config)
  scores = judge_scores(candidates, capacity, judge)
  best = int(np.argmax(scores))
  names = [UNCHANGED] + [m.description for m in moves]
  as_json = [s if np.isfinite(s) else None for s in scores]  # None: a judging demonstration fits no stack
  return candidates[best], {"round": round_index, "kept": names[best], "log_likelihood_per_step": as_json[best],
                            "candidates": [[n, s] for n, s in zip(names, as_json)]}


def search(hierarchy: PHPHierarchy, capacity: tuple[int, ...], demos: Demonstration, judge: Demonstration,
           config: TrainConfig, rounds: list[dict], on_round: Callable[[PHPHierarchy, list[dict]], None]
           ) -> tuple[PHPHierarchy, list[dict]]:
  """The search from hierarchy, `rounds` (the log entries of rounds already made, [] at the start) going on
  until config.split_rounds or a round that keeps the unchanged hierarchy; on_round(hierarchy, rounds) after
  each round (to log and checkpoint it). Returns the kept hierarchy and every round's entry."""
  rounds = list(rounds)
  while len(rounds) < config.split_rounds and not (rounds and rounds[-1]["kept"] == UNCHANGED):
    hierarchy, entry = search_round(hierarchy, capacity, demos, judge, config, len(rounds))
    rounds.append(entry)
    on_round(hierarchy, rounds)
  return hierarchy, rounds
