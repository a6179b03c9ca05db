"""Weak-only NanoCraft, started from a segmentation of the actions into calls: for the first HINT_ITERS of
the default joint run's 2,000 iterations, each training demonstration's level-1 and level-2 counters are
given as a partial annotation (every procedure left unknown); the remaining iterations are weak-only. The
annealing, validation and snapshot are the default run's.

SOURCE "loops": the loop segmentation, from the actions alone, under two assumptions: (1) an elementary
action that never follows itself in the training demonstrations continues the call before it (its level-2
counter is the previous step's plus one); every other action starts a level-2 call; (2) a level-1 call
repeats one kind of level-2 call: a level-2 call that starts with the same action as the one before it
continues that level-1 call, any other starts a new one. "attach=A,B": the same with assumption (1)'s
actions given (action ids) instead of found. "supervisor": the supervisor's own counters (what the
segmentation is compared with).

usage: python experiments/segmentation_hints.py SEED OUT HINT_ITERS SOURCE (OUT gets the model, for
experiments.decode, and hints.json: the test accuracy, the loss after the hints are dropped, and how many
steps' hinted counters are the supervisor's)
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

taus, lengths, actions = np.asarray(demos.counters), np.asarray(demos.length), np.asarray(demos.actions)[..., 0]


def loop_counters(attached):
  """[B, T, 2] level-1 and level-2 counters of the loop segmentation (UNKNOWN on padding)."""
  counters = np.full(taus.shape[:2] + (2,), UNKNOWN, taus.dtype)
  for b, n in enumerate(lengths):
    first = None
    for t in range(n):
      if t > 0 and actions[b, t] in attached:
        counters[b, t] = counters[b, t - 1, 0], counters[b, t - 1, 1] + 1
      else:
        counters[b, t] = (counters[b, t - 1, 0] + 1 if actions[b, t] == first else 0), 0
        first = actions[b, t]
  return counters


valid = np.arange(taus.shape[1]) < lengths[:, None]
if source == "supervisor":
  hinted_level_counters = np.where(valid[..., None], taus[..., 1:], UNKNOWN)
elif source == "loops":
  repeated = {a for b, n in enumerate(lengths) for a, c in zip(actions[b, :n - 1], actions[b, 1:n]) if a == c}
  attached = set(np.unique(actions[valid]).tolist()) - repeated
  hinted_level_counters = loop_counters(attached)
elif source.startswith("attach="):
  attached = {int(a) for a in source[len("attach="):].split(",")}
  hinted_level_counters = loop_counters(attached)
else:
  raise SystemExit(f"unknown SOURCE {source!r}")
hinted_taus = np.full_like(taus, UNKNOWN)
hinted_taus[..., 1:] = hinted_level_counters
same = (hinted_taus[..., 1:] == taus[..., 1:]).all(-1)[valid].mean()
hinted = demos._replace(procedures=np.full_like(taus, UNKNOWN), counters=hinted_taus,
                        strong=np.ones(len(lengths), bool))
print("capacity", capacity, "steps whose hinted counters are the supervisor's", same, flush=True)


def loss(h, iteration, buckets):
  temperature = objective.annealed_temperature(config.anneal_temperature, iteration, config.iterations)
  return objective.stack_loss(h, buckets, capacity, 1.0, temperature)


log = {"seed": seed, "hint_iters": hint_iters, "source": source, "hinted_counters_supervisors": float(same)}
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
