"""Split-and-merge search from a trained weak-only run: per round, per level below the root, the least-used
procedure q is replaced by a copy of the most-used p (q's calls merged away, p split in two; the parent's
call probability of p shared between p and its copy), each candidate and the unchanged model trained
`iters` more weak-only iterations, and the one with the best validation likelihood kept.

usage: python experiments/split_merge.py RUN SEED OUT ROUNDS ITERS (RUN: a finished weak-only NanoCraft run of
that seed; OUT: where the chosen model, its test accuracy and each round's choice are written)
"""
import json
import math
import sys
import time

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import fitting
from php_jax.analysis import decoding
from php_jax.data import agreement
from php_jax.envs import datasets, evaluation, tasks
from php_jax.training import checkpoint, joint, objective

run, seed, out, rounds, iters = sys.argv[1], int(sys.argv[2]), sys.argv[3], int(sys.argv[4]), int(sys.argv[5])
start = time.time()
task = tasks.get("nanocraft")
_, hierarchy = checkpoint.load_policy(run)
model_json = json.load(open(f"{run}/model.json"))
capacity = tuple(model_json["capacity"])
demos = datasets.training_demos(task, seed, 64, 0)
validation = datasets.problem_demonstrations(task, task.validation_problems(seed + 10_000, 50), 0)
buckets = joint._buckets(demos, 4)
depth = len(hierarchy.levels)


def loss(h, b):
  return objective.stack_loss(h, b, capacity, 1.0)


def train(h, n):
  progress = fitting.fit(h, loss, fitting.Schedule(n, 3e-3, n), fitting.Hooks(log=lambda row: None),
                         args=(buckets,))
  return progress.losses[-1][1]


def per_step(h, batch):
  decoded = decoding.decode(h, capacity, batch)
  return decoding.log_likelihood_per_step(decoded.log_likelihood, np.asarray(batch.length))[0], decoded


def usage(decoded, batch):
  """Per level 1..depth-1: calls per procedure (Viterbi stacks of batch)."""
  counts = [np.zeros(len(level.termination.biases[0][...])) for level in hierarchy.levels]
  for b, n in enumerate(np.asarray(batch.length)):
    procs, taus = decoded.procedures[b, :n], decoded.counters[b, :n]
    for level in range(1, depth):
      starts = agreement.call_starts(procs, taus, level)
      np.add.at(counts[level], procs[starts, level], 1)
  return counts


def copy_procedure(h, level, p, q, key):
  """Procedure q of `level` becomes a copy of p (a little noise on the copy); the parent shares p's call
  probability between the two."""
  php = h.levels[level]
  for mlp in (php.operation, php.termination):
    for params in (mlp.kernels, mlp.biases):
      for param in params:
        value = param[...]
        key, sub = jax.random.split(key)
        noise = 0.01 * jnp.std(value[p]) * jax.random.normal(sub, value[p].shape)
        param.value = value.at[q].set(value[p] + noise)
  parent = h.levels[level - 1].operation
  kernel, bias = parent.kernels[-1], parent.biases[-1]
  kernel.value = kernel[...].at[:, :, q].set(kernel[...][:, :, p])
  shared = bias[...][:, p] - math.log(2)
  bias.value = bias[...].at[:, p].set(shared).at[:, q].set(shared)


key = jax.random.key(seed)
val_ll, decoded = per_step(hierarchy, validation)
log = {"start_val_ll": val_ll, "rounds": []}
print("start", val_ll, flush=True)
for r in range(rounds):
  counts = usage(decoding.decode(hierarchy, capacity, demos), demos)
  candidates = [("none", None)]
  for level in range(1, depth):
    p, q = int(np.argmax(counts[level])), int(np.argmin(counts[level]))
    candidates.append((f"level {level}: {q} <- copy of {p}", (level, p, q)))
  results = []
  for name, move in candidates:
    h = nnx.clone(hierarchy)
    if move:
      key, sub = jax.random.split(key)
      copy_procedure(h, *move, sub)
    train_loss = train(h, iters)
    ll, _ = per_step(h, validation)
    results.append((ll if ll is not None else -np.inf, name, h, train_loss))
    print(r, name, "val ll", ll, "train loss", train_loss, [c.astype(int).tolist() for c in counts[1:]], flush=True)
  ll, name, hierarchy, train_loss = max(results, key=lambda x: x[0])
  log["rounds"].append({"chosen": name, "val_ll": ll, "train_loss": train_loss,
                        "all": [(n, float(l), float(t)) for l, n, _, t in results]})
  print("round", r, "chose", name, ll, flush=True)

checkpoint.save_hierarchy(out, "nanocraft", hierarchy, tuple(model_json["hidden"]), list(capacity))
test = task.test_problems(seed + datasets.SEED_OFFSETS["test"], 1000, None)
log["test_accuracy"] = evaluation.accuracy(task, hierarchy, test)
log["seconds"] = time.time() - start
json.dump(log, open(f"{out}/reassign.json", "w"), indent=1)
print("test accuracy", log["test_accuracy"], "seconds", log["seconds"], flush=True)
