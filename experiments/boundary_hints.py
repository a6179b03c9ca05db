"""Weak-only NanoCraft, started from a flat segmentation: for the first HINT_ITERS of the default joint run's
2,000 iterations, each training demonstration's level-1 call boundaries are given as a partial annotation
(at a boundary step the level-1 and level-2 counters are 0; every procedure, and every other counter, is
left unknown); the remaining iterations are weak-only. The annealing, validation and snapshot are the
default run's. SOURCE "supervisor" takes the boundaries from the supervisor's stacks (the best any flat
segmentation could give); "supervisor_both" gives its level-2 boundaries too: every level-1 and level-2
counter is given, and only the procedures are left to find; "supervisor_level2" gives the level-2 counters
alone (level 2's boundaries).

usage: python experiments/boundary_hints.py SEED OUT HINT_ITERS SOURCE (OUT gets the model, for
experiments.decode, and hints.json: the test accuracy and the loss before and after the hints are dropped)
"""
import json
import sys
import time

import numpy as np
from flax import nnx

from php_jax import fitting
from php_jax.demos import UNKNOWN
from php_jax.envs import datasets, evaluation, tasks
from php_jax.training import call_graph, checkpoint, joint, objective, train
from php_jax.training.config import TrainConfig

seed, out, hint_iters, source = int(sys.argv[1]), sys.argv[2], int(sys.argv[3]), sys.argv[4]
start = time.time()
task = tasks.get("nanocraft")
d = task.defaults
config = train.in_mode(TrainConfig(seed=seed, anneal_temperature=1.5, hidden=d.hidden,
                                   tau_in_termination=d.tau_in_termination, call_graph=d.call_graph), "joint")
demos = datasets.training_demos(task, seed, 64, 0)
config = train.prepare(task.spec, demos, config)
hierarchy = train.make_hierarchy(task.spec, config, call_graph.resolve(config.call_graph, demos, task.spec))
capacity = joint.joint_capacity(demos, task.spec, config)
validation = task.validation_problems(seed + datasets.SEED_OFFSETS["validation"], 50)

taus, lengths = np.asarray(demos.counters), np.asarray(demos.length)
starts = (taus[..., 1] == 0) & (taus[..., 2] == 0) & (np.arange(taus.shape[1]) < lengths[:, None])
hinted_taus = np.full_like(taus, UNKNOWN)
if source == "supervisor":
  hinted_taus[starts, 1] = hinted_taus[starts, 2] = 0
elif source == "supervisor_both":
  hinted_taus[..., 1:] = taus[..., 1:]
elif source == "supervisor_level2":
  hinted_taus[..., 2] = taus[..., 2]
else:
  raise SystemExit(f"unknown SOURCE {source!r}")
hinted = demos._replace(procedures=np.full_like(taus, UNKNOWN), counters=hinted_taus,
                        strong=np.ones(len(lengths), bool))
print("capacity", capacity, "boundaries per demonstration", starts.sum() / len(lengths), flush=True)


def loss(h, iteration, buckets):
  temperature = objective.annealed_temperature(config.anneal_temperature, iteration, config.iterations)
  return objective.stack_loss(h, buckets, capacity, 1.0, temperature)


log = {"seed": seed, "hint_iters": hint_iters, "source": source}
hooks = fitting.Hooks(lambda it, l: evaluation.accuracy(task, hierarchy, validation), print)
schedule = config.schedule()
progress = fitting.fit(hierarchy, loss, schedule._replace(iterations=hint_iters), hooks,
                       args=(joint._buckets(hinted, config.length_buckets),), pass_iteration=True)
weak = joint._buckets(demos, config.length_buckets)
nnx.update(hierarchy, progress.params)  # fit left the best-validated snapshot; the run goes on from the last
log["weak_loss_after_hints"] = float(objective.stack_loss(hierarchy, weak, capacity, 1.0))
progress = fitting.fit(hierarchy, loss, schedule, hooks, resume=progress, args=(weak,), pass_iteration=True)
log["final_loss"] = float(objective.stack_loss(hierarchy, weak, capacity, 1.0))
log["best_iteration"] = progress.best_iteration
checkpoint.save_hierarchy(out, "nanocraft", hierarchy, config.hidden, list(capacity))
test = task.test_problems(seed + datasets.SEED_OFFSETS["test"], 1000, None)
log["test_accuracy"] = evaluation.accuracy(task, hierarchy, test)
log["seconds"] = time.time() - start
json.dump(log, open(f"{out}/hints.json", "w"), indent=1)
print(json.dumps(log), flush=True)
