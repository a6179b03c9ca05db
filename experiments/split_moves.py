"""Split-by-caller search from a trained weak-only run: per round, each level-2 procedure p that several
level-1 procedures call (in the Viterbi stacks of the training demonstrations) gives one candidate move, in
which its second-busiest caller c calls a copy of p instead (the least-used level-2 procedure q becomes the
copy, its own calls given up; c's call probabilities of p and q are swapped, so every other stack keeps its
probability). Each level-1 procedure p that the root calls at several of its counters gives one more: the
least-used level-1 procedure q becomes a copy of p, and the calls of p that the root makes at its
second-busiest counter for p are q's; as the root's networks cannot be changed for one counter alone, the
move is taught: the first HINT iterations of its training give the relabelled Viterbi level-1 procedures as
a partial annotation. Each candidate (at most 3 of each kind, the busiest p first) and the unchanged model
train ITERS more weak-only iterations, and the one with the best validation likelihood is kept.

usage: python experiments/split_moves.py RUN SEED OUT ROUNDS ITERS HINT (RUN: a finished weak-only NanoCraft
run of that seed; OUT: where the chosen model, its test accuracy and each round's choice are written)
"""
import json
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import fitting
from php_jax.analysis import decoding
from php_jax.data import agreement
from php_jax.demos import UNKNOWN
from php_jax.envs import datasets, evaluation, tasks
from php_jax.training import checkpoint, joint, objective

run, out = sys.argv[1], sys.argv[3]
seed, rounds, iters, hint = (int(a) for a in (sys.argv[2], *sys.argv[4:7]))
start = time.time()
task = tasks.get("nanocraft")
_, hierarchy = checkpoint.load_policy(run)
model_json = json.load(open(f"{run}/model.json"))
capacity = tuple(model_json["capacity"])
demos = datasets.training_demos(task, seed, 64, 0)
validation = datasets.problem_demonstrations(task, task.validation_problems(seed + 10_000, 50), 0)
buckets = joint._buckets(demos, 4)
LEVEL = 2


def loss(h, b):
  return objective.stack_loss(h, b, capacity, 1.0)


def train(h, n, hinted=None):
  if hinted is not None:
    fitting.fit(h, loss, fitting.Schedule(hint, 3e-3, hint), fitting.Hooks(log=lambda row: None),
                args=(joint._buckets(hinted, 4),))
    n -= hint
  progress = fitting.fit(h, loss, fitting.Schedule(n, 3e-3, n), fitting.Hooks(log=lambda row: None),
                         args=(buckets,))
  return progress.losses[-1][1]


def copy_procedure(h, level, p, q, key):
  """Level `level`'s procedure q becomes a copy of p, with a little noise."""
  php = h.levels[level]
  for mlp in (php.operation, php.termination):
    for params in (mlp.kernels, mlp.biases):
      for param in params:
        value = param[...]
        key, sub = jax.random.split(key)
        noise = 0.01 * jnp.std(value[p]) * jax.random.normal(sub, value[p].shape)
        param.value = value.at[q].set(value[p] + noise)


def level1_moves(h, batch):
  """Candidate level-1 moves (p, q, root counter) and the hinted demonstrations for each."""
  decoded = decoding.decode(h, capacity, batch)
  num = len(h.levels[1].termination.biases[0][...])
  counts, used = {}, np.zeros(num, int)
  for b, n in enumerate(np.asarray(batch.length)):
    procs, taus = decoded.procedures[b, :n], decoded.counters[b, :n]
    for t in np.flatnonzero(agreement.call_starts(procs, taus, 1)):
      counts.setdefault(int(procs[t, 1]), {}).setdefault(int(taus[t, 0]), 0)
      counts[int(procs[t, 1])][int(taus[t, 0])] += 1
      used[procs[t, 1]] += 1
  moves = []
  for p in np.argsort(-used):
    by_counter = sorted(counts.get(int(p), {}).items(), key=lambda kv: -kv[1])
    if len(by_counter) > 1:
      q = int(min((c for c in range(num) if c != p), key=lambda c: used[c]))
      tau = by_counter[1][0]
      procedures = np.full(np.shape(batch.procedures), UNKNOWN, np.int32)
      for b, n in enumerate(np.asarray(batch.length)):
        level1, root_tau = decoded.procedures[b, :n, 1].copy(), decoded.counters[b, :n, 0]
        level1[level1 == q] = UNKNOWN
        level1[(level1 == p) & (root_tau == tau)] = q
        procedures[b, :n, 1] = level1
      hinted = batch._replace(procedures=procedures, counters=np.full_like(procedures, UNKNOWN),
                              strong=np.ones(len(batch.length), bool))
      moves.append((f"level 1: {q} <- copy of {p} for root counter {tau}", (int(p), q), hinted))
  return moves


def per_step(h, batch):
  decoded = decoding.decode(h, capacity, batch)
  return decoding.log_likelihood_per_step(decoded.log_likelihood, np.asarray(batch.length))[0]


def calls_by_caller(h, batch):
  """[K_1, K_2]: how often each level-1 procedure calls each level-2 procedure (Viterbi stacks of batch)."""
  decoded = decoding.decode(h, capacity, batch)
  counts = np.zeros((len(h.levels[LEVEL - 1].termination.biases[0][...]),
                     len(h.levels[LEVEL].termination.biases[0][...])), int)
  for b, n in enumerate(np.asarray(batch.length)):
    procs, taus = decoded.procedures[b, :n], decoded.counters[b, :n]
    starts = agreement.call_starts(procs, taus, LEVEL)
    np.add.at(counts, (procs[starts, LEVEL - 1], procs[starts, LEVEL]), 1)
  return counts


def split(h, p, q, caller, key):
  """Level-2 procedure q becomes a copy of p (a little noise on the copy), and `caller` calls q where it
  called p (its logits of p and q swapped)."""
  copy_procedure(h, LEVEL, p, q, key)
  parent = h.levels[LEVEL - 1].operation
  kernel, bias = parent.kernels[-1], parent.biases[-1]
  k, b = kernel[...], bias[...]
  kernel.value = k.at[caller, :, q].set(k[caller, :, p]).at[caller, :, p].set(k[caller, :, q])
  bias.value = b.at[caller, q].set(b[caller, p]).at[caller, p].set(b[caller, q])


key = jax.random.key(seed)
log = {"start_val_ll": per_step(hierarchy, validation), "start_loss": float(loss(hierarchy, buckets)), "rounds": []}
print("start", log, flush=True)
for r in range(rounds):
  counts = calls_by_caller(hierarchy, demos)
  used = counts.sum(0)
  candidates = [("none", None, None)]
  for p in np.argsort(-used):
    callers = np.argsort(-counts[:, p])
    if counts[callers[1], p] > 0:
      q = int(min((c for c in range(len(used)) if c != p), key=lambda c: used[c]))
      candidates.append((f"{q} <- copy of {p} for caller {callers[1]}", (int(p), q, int(callers[1])), None))
  candidates = candidates[:4] + level1_moves(hierarchy, demos)[:3]
  results = []
  for name, move, hinted in candidates:
    h = nnx.clone(hierarchy)
    if move:
      key, sub = jax.random.split(key)
      if hinted is not None:
        copy_procedure(h, 1, *move, sub)
      else:
        split(h, *move, sub)
    moved_loss = float(loss(h, buckets))
    train_loss = train(h, iters, hinted)
    ll = per_step(h, validation)
    results.append((ll if ll is not None else -np.inf, name, h, train_loss))
    print(r, name, "loss after the move", moved_loss, "val ll", ll, "train loss", train_loss, counts.tolist(),
          flush=True)
  ll, name, hierarchy, train_loss = max(results, key=lambda x: x[0])
  log["rounds"].append({"chosen": name, "val_ll": ll, "train_loss": train_loss,
                        "all": [(n, float(l), float(t)) for l, n, _, t in results]})
  print("round", r, "chose", name, ll, flush=True)

checkpoint.save_hierarchy(out, "nanocraft", hierarchy, tuple(model_json["hidden"]), list(capacity))
test = task.test_problems(seed + datasets.SEED_OFFSETS["test"], 1000, None)
log["test_accuracy"] = evaluation.accuracy(task, hierarchy, test)
log["seconds"] = time.time() - start
json.dump(log, open(f"{out}/split.json", "w"), indent=1)
print("test accuracy", log["test_accuracy"], "seconds", log["seconds"], flush=True)
