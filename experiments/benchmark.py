r"""Benchmarks as commands: ratios against baselines measured in the same process.

  python -m experiments.benchmark estep     # E-step: ours vs a plain log-space scan vs dynamax's smoother
  python -m experiments.benchmark estep_grad  # the E-step's gradient: jax.grad of log P(ξ) vs the values alone
  python -m experiments.benchmark rollout --task=NAME --size=1000  # oracle rollouts: steps per second
  python -m experiments.benchmark train_step --task=NAME --hidden=64  # one EG iteration, split
  python -m experiments.benchmark scaling --task=NAME --hidden=32  # one EG step on 1 vs all devices; seeds vmapped
  python -m experiments.benchmark act --policy=RUN --env=ENV --num_envs=64  # a policy in a Gymnasium env vs the env
  python -m experiments.benchmark demo_files --num_demos=300  # the binary demonstration format vs JSON lines
  python -m experiments.benchmark fast_path --num_demos=1000  # one EG update on BabyAI-sized data, each speed-up
  python -m experiments.benchmark fast_path --demos=F --hierarchy=H --env=E  # the same on your demonstrations
  python -m experiments.benchmark many_demos --demos=F --hierarchy=H --copies=1,10,100  # fit's memory and speed

estep times values + marginals for B demonstrations of T steps (vmapped, jitted) at the paper's sizes and beyond,
checks that the three agree on log P(ξ), and prints lattice cells (B·T·K·C) per second and ratios.
demo_files writes and reads N synthetic demonstrations of BabyAI's size as JSON lines and as a binary set
(`php_jax.data.shards`), checks that both read to the same arrays, and prints the sizes and times and their
ratios.
many_demos runs experiments.fit, with its defaults, on 1, 10, 100... copies of a demonstration file, each in a
process of its own: its peak memory, seconds per update, steps per second and wall time.
"""
from __future__ import annotations

import dataclasses
import importlib.util
import itertools
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np
from absl import app, flags
from flax import nnx

import php_jax
from experiments.common import cli
from php_jax import executor, fitting, sharding
from php_jax.data import demo_files, files, shards, views
from php_jax.demos import Demonstration
from php_jax.envs import datasets, tasks
from php_jax.hierarchy import HierarchySpec
from php_jax.training import joint, levelwise, networks, objective
from php_jax.training.config import TrainConfig, balanced_strong_weight

_SIZES = flags.DEFINE_string(
    "sizes", "160x80x3x8,160x200x6x16,32x400x6x32,16x10000x3x8,4096x200x6x16",
    "Comma-separated BxTxKxC for estep.")
_MIN_TIME = flags.DEFINE_float("min_time", 1.0, "Seconds of repetitions per measurement (median taken).")
_DYNAMAX_MAX_BYTES = flags.DEFINE_float("dynamax_max_gb", 4.0, "Skip dynamax above this working set (GB).")
_OUT = flags.DEFINE_string("out", None, "Optional JSON file for the results.")
_TASK = flags.DEFINE_string("task", None, "rollout, train_step, scaling: the task (what experiments.train --task "
                            "takes).")
_SIZE = flags.DEFINE_integer("size", 1000, "rollout: problem size (digits, array length; ignored by tasks with "
                             "one size).")
_PROBLEMS = flags.DEFINE_integer("problems", 100, "rollout: number of problems.")
_HIDDEN = flags.DEFINE_list("hidden", ["64"], "train_step, scaling: hidden layer sizes of the PHP networks.")
_ROOT = flags.DEFINE_enum("root", "lstm", ["lstm", "mlp"], "train_step, scaling: root network.")
_NUM_STRONG = flags.DEFINE_integer("num_strong", 3, "train_step, scaling: annotated demonstrations of the training "
                                   "set.")
_NUM_DEMOS = flags.DEFINE_integer("num_demos", None, "scaling: demonstrations of the training set (default: the "
                                  "task's); demo_files, fast_path: synthetic demonstrations (default: 300).")
_POLICY = flags.DEFINE_string("policy", None, "act: a workdir of experiments.fit.")
_ENV = flags.DEFINE_string("env", None, "act, many_demos, fast_path: the Gymnasium environment (what "
                           "experiments.act and experiments.fit --env take).")
_DEMOS = flags.DEFINE_string("demos", None, "many_demos: the demonstrations to copy; fast_path: the demonstrations "
                             "timed (default: synthetic ones). What experiments.fit --demos takes.")
_HIERARCHY = flags.DEFINE_string("hierarchy", None, "many_demos, fast_path: their hierarchy file.")
_COPIES = flags.DEFINE_list("copies", ["1", "10", "100"], "many_demos: copies of --demos each fit trains on.")
_ITERATIONS = flags.DEFINE_integer("iterations", 300, "many_demos: each fit's --iterations.")
_NUM_ENVS = flags.DEFINE_integer("num_envs", 64, "act: copies of the environment stepped together.")
_EPISODES = flags.DEFINE_integer("episodes", 1000, "act: episodes timed.")
_BATCH = flags.DEFINE_integer("batch_size", 32, "fast_path: demonstrations per minibatch update.")
_SEEDS = flags.DEFINE_integer("seeds", 5, "scaling: parameter sets whose gradients are taken as one vmapped program "
                              "and one after another.")


def _median_seconds(fn, *args) -> float:
  jax.block_until_ready(fn(*args))  # compile
  start = time.perf_counter()
  jax.block_until_ready(fn(*args))
  first = time.perf_counter() - start
  times = [first]
  for _ in range(min(20, max(0, int(_MIN_TIME.value / max(first, 1e-9)) - 1))):
    start = time.perf_counter()
    jax.block_until_ready(fn(*args))
    times.append(time.perf_counter() - start)
  return statistics.median(times)


def plain_forward_backward(log_root, log_op, log_stop, log_cont):
  """The appendix's recursions, straight: log-space α and β scans, marginals exp(α + β − log Z)."""
  num_steps, num_procs, capacity = log_op.shape
  neg_inf_col = jnp.full((num_procs, 1), -jnp.inf)
  alpha0 = jnp.full((num_procs, capacity), -jnp.inf).at[:, 0].set(log_root[0])

  def forward(alpha, t):
    emit = alpha + log_op[t]
    stop_mass = jax.nn.logsumexp(emit + log_stop[t])
    nxt = jnp.concatenate([(stop_mass + log_root[t + 1])[:, None], (emit + log_cont[t])[:, :-1]], axis=1)
    return nxt, alpha

  last_alpha, alphas = jax.lax.scan(forward, alpha0, jnp.arange(num_steps - 1))
  alphas = jnp.concatenate([alphas, last_alpha[None]])
  log_z = jax.nn.logsumexp(last_alpha + log_op[-1] + log_stop[-1])

  def backward(beta_next, t):
    pushed = jax.nn.logsumexp(log_root[t + 1] + beta_next[:, 0])
    shifted = jnp.concatenate([beta_next[:, 1:], neg_inf_col], axis=1)
    beta = log_op[t] + jnp.logaddexp(log_stop[t] + pushed, log_cont[t] + shifted)
    w = jnp.exp(alphas[t] + log_op[t] + log_cont[t] + shifted - log_z)
    return beta, (beta, w)

  beta_last = log_op[-1] + log_stop[-1]
  _, (betas, w) = jax.lax.scan(backward, beta_last, jnp.arange(num_steps - 1), reverse=True)
  betas = jnp.concatenate([betas, beta_last[None]])
  w = jnp.concatenate([w, jnp.zeros((1, num_procs, capacity))])
  return log_z, jnp.exp(alphas + betas - log_z), w


def dynamax_smoother(log_root, log_op, log_stop, log_cont):
  """dynamax's hmm_smoother on the flattened K·C states, time-varying transitions built per step."""
  from dynamax.hidden_markov_model import inference as hmm  # optional dependency (pip install .[bench])
  num_steps, num_procs, capacity = log_op.shape
  states = num_procs * capacity
  cont_target = jnp.eye(states, k=1) * (jnp.arange(states) % capacity < capacity - 1)[:, None]
  push_target = (jnp.arange(states) % capacity == 0).astype(jnp.float32)

  def transition(t):
    stop = jnp.exp(log_stop[t]).reshape(states, 1)
    cont = jnp.exp(log_cont[t]).reshape(states, 1)
    root_next = jnp.repeat(jnp.exp(log_root[t + 1]), capacity) * push_target
    return stop * root_next[None, :] + cont * cont_target

  emissions = log_op.reshape(num_steps, states).at[-1].add(log_stop[-1].reshape(states))
  initial = (jnp.exp(log_root[0])[:, None] * (jnp.arange(capacity) == 0)[None, :]).reshape(states)
  post = hmm.hmm_smoother(initial, None, emissions, transition_fn=transition)  # also pairwise posteriors
  return post.marginal_loglik, post.smoothed_probs


def _random_inputs(key, batch, num_steps, num_procs, capacity):
  k1, k2, k3 = jax.random.split(key, 3)
  log_root = jax.nn.log_softmax(jax.random.normal(k1, (batch, num_steps, num_procs)), axis=-1)
  log_op = jax.nn.log_sigmoid(2.0 * jax.random.normal(k2, (batch, num_steps, num_procs, capacity)))
  z = jax.random.normal(k3, (batch, num_steps, num_procs, capacity))
  return log_root, log_op, jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)


def bench_estep():
  ours = jax.jit(jax.vmap(lambda *a: tuple(php_jax.forward_backward(*a))))
  plain = jax.jit(jax.vmap(plain_forward_backward))
  dyn = jax.jit(jax.vmap(dynamax_smoother))
  rows = []
  have_dynamax = importlib.util.find_spec("dynamax") is not None
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()})"
        + ("" if have_dynamax else "; dynamax not installed (pip install -e .[bench]): its column is skipped"))
  header = f"{'B x T x K x C':>20} {'ours Gcell/s':>13} {'plain':>8} {'dynamax':>8} {'vs plain':>9} {'vs dynamax':>11}"
  print(header)
  for size in _SIZES.value.split(","):
    batch, num_steps, num_procs, capacity = map(int, size.split("x"))
    cells = batch * num_steps * num_procs * capacity
    inputs = _random_inputs(jax.random.key(0), batch, num_steps, num_procs, capacity)
    t_ours = _median_seconds(ours, *inputs)
    t_plain = _median_seconds(plain, *inputs)
    ll_ours, ll_plain = ours(*inputs)[0], plain(*inputs)[0]
    agree = float(jnp.max(jnp.abs(ll_ours - ll_plain) / jnp.maximum(1.0, jnp.abs(ll_plain))))
    dyn_bytes = 4 * batch * num_steps * (num_procs * capacity) ** 2 + 16 * cells  # pairwise posteriors
    t_dyn = None
    if have_dynamax and dyn_bytes <= _DYNAMAX_MAX_BYTES.value * 1e9:
      t_dyn = _median_seconds(dyn, *inputs)
      agree = max(agree, float(jnp.max(jnp.abs(ll_ours - dyn(*inputs)[0]) / jnp.maximum(1.0, jnp.abs(ll_ours)))))
    row = {"size": size, "cells": cells, "ours_s": t_ours, "plain_s": t_plain, "dynamax_s": t_dyn,
           "ours_gcells_per_s": cells / t_ours / 1e9, "speedup_vs_plain": t_plain / t_ours,
           "speedup_vs_dynamax": t_dyn / t_ours if t_dyn else None, "max_rel_loglik_diff": agree}
    rows.append(row)
    dyn_text = f"{cells / t_dyn / 1e9:8.3f}" if t_dyn else f"{'skipped':>8}"
    ratio_text = f"{row['speedup_vs_dynamax']:10.1f}x" if t_dyn else f"{'-':>11}"
    print(f"{size:>20} {row['ours_gcells_per_s']:13.3f} {cells / t_plain / 1e9:8.3f} {dyn_text} "
          f"{row['speedup_vs_plain']:8.2f}x {ratio_text}   (log P agree to {agree:.1e})", flush=True)
  return rows


def bench_estep_grad():
  """Cost of jax.grad of Σ log P(ξ) w.r.t. the four inputs, against values + marginals alone (ours) and
  against the plain reference's autodiff gradient, at the same sizes as estep."""
  ours = jax.jit(jax.vmap(lambda *a: tuple(php_jax.forward_backward(*a))))
  ours_grad = jax.jit(jax.grad(lambda *a: jnp.sum(jax.vmap(lambda *x: php_jax.forward_backward(*x).log_likelihood)(*a)),
                               argnums=(0, 1, 2, 3)))
  plain_grad = jax.jit(jax.grad(lambda *a: jnp.sum(jax.vmap(plain_forward_backward)(*a)[0]), argnums=(0, 1, 2, 3)))
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()})")
  print(f"{'B x T x K x C':>20} {'values ms':>10} {'grad ms':>9} {'grad/values':>12} {'plain grad ms':>14}")
  rows = []
  for size in _SIZES.value.split(","):
    batch, num_steps, num_procs, capacity = map(int, size.split("x"))
    inputs = _random_inputs(jax.random.key(0), batch, num_steps, num_procs, capacity)
    t_values = _median_seconds(ours, *inputs)
    t_grad = _median_seconds(ours_grad, *inputs)
    t_plain = _median_seconds(plain_grad, *inputs)
    rows.append({"size": size, "values_s": t_values, "grad_s": t_grad, "plain_grad_s": t_plain})
    print(f"{size:>20} {t_values * 1e3:10.1f} {t_grad * 1e3:9.1f} {t_grad / t_values:11.2f}x {t_plain * 1e3:14.1f}",
          flush=True)
  return rows


def bench_rollout():
  task = _task()
  problems = task.test_problems(0, _PROBLEMS.value, _SIZE.value)
  states, budget = task.states_and_budget(problems)
  keys = jax.random.split(jax.random.key(0), len(problems))
  rows = []
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); "
        f"{len(problems)} {task.name} problems of size {_SIZE.value}")
  for record in (False, True):
    run = lambda s, k, record=record: executor.rollout_batch(task.oracle, task.spec, task.env, s, k, budget,
                                                           record)
    seconds = _median_seconds(run, states, keys)
    out = run(states, keys)
    steps = int(np.asarray(out.length).sum())
    assert bool(np.all(out.terminated)), "the oracle failed a problem"
    rows.append({"record": record, "steps": steps, "seconds": seconds, "steps_per_s": steps / seconds})
    print(f"record={record!s:5}: {steps} elementary steps in {seconds:.3f} s = {steps / seconds:,.0f} steps/s")
  return rows


def bench_train_step():
  """Where one training iteration's time goes at the task's lowest level (the costliest level: every
  elementary step, in length buckets): the jitted gradient of the whole EG loss against the same loss with
  the lattice replaced by a plain sum of its inputs (the networks alone) and against the root network alone."""
  task = _task()
  demos = datasets.training_demos(task, 1, task.defaults.num_demos, _NUM_STRONG.value)
  view = views.lowest_view(demos, task.spec.num_levels)
  config = TrainConfig(hidden=tuple(int(h) for h in _HIDDEN.value), root=_ROOT.value,
                             strong_weight=balanced_strong_weight(demos.strong))
  level = task.spec.num_levels - 1
  model = objective.LevelModel(networks.make_hierarchy(task.spec, config).levels[level],
                           networks.make_root(task.spec, level, config))
  buckets = [views.device_view(b) for b in views.length_buckets(view, config.length_buckets)]
  capacity = levelwise.level_capacity(view, level, config)
  graphdef, params, rest = nnx.split(model, nnx.Param, ...)

  def networks_only(m):  # the lattice's inputs, summed where finite: the same networks, no E-step
    total = 0.0
    for b in buckets:
      inputs = jax.vmap(lambda view: objective.lattice_inputs(m, view, capacity))(b)
      total = total + sum(jnp.sum(jnp.where(jnp.isfinite(x), x, 0.0)) for x in inputs[:4])  # not the length
    return total

  losses = {"EG loss (networks + lattice)": lambda m: objective.level_loss(m, buckets, capacity, config.strong_weight),
            "networks only": networks_only,
            "root network only": lambda m: sum(jnp.sum(jax.vmap(m.root)(b.observations[:, :-1])) for b in buckets)}
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); {task.name} level {level}: "
        f"{len(demos.length)} views in {len(buckets)} buckets, C = {capacity}, hidden {config.hidden}, root {config.root}")
  rows, first = [], None
  for name, loss in losses.items():
    grad = jax.jit(jax.value_and_grad(lambda p, loss=loss: loss(nnx.merge(graphdef, p, rest))))
    seconds = _median_seconds(grad, params)
    first = first or seconds
    rows.append({"what": name, "ms": seconds * 1e3, "fraction_of_full": seconds / first})
    print(f"{name:>30}: {seconds * 1e3:8.1f} ms per gradient  ({seconds / first:.2f} of the full loss)")
  return rows


def bench_scaling():
  """One EG step (jitted value and gradient of the loss) on one device against the length buckets split over
  every device (`sharding`), per level of the level-wise loss and for the joint loss; then the gradients of
  --seeds independent parameter sets over the same data, as one vmapped program against one call per seed,
  each waited for before the next (one device). Levels above the lowest see the supervisor's call sequences,
  the views a right decoding gives."""
  task = _task()
  spec, num_demos = task.spec, _NUM_DEMOS.value or task.defaults.num_demos
  demos = datasets.training_demos(task, 1, num_demos, min(_NUM_STRONG.value, num_demos))
  config = TrainConfig(hidden=tuple(int(h) for h in _HIDDEN.value), root=_ROOT.value,
                             strong_weight=balanced_strong_weight(demos.strong),
                             length_buckets=views.bucket_count(demos.length))
  mesh, num_devices = sharding.data_mesh(), len(jax.devices())
  annotated = demos._replace(strong=np.ones_like(demos.strong))  # every demonstration's true views, above too
  level_views = views.annotated_views(annotated, spec.num_levels)
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}) x {num_devices}; {task.name}: "
        f"{num_demos} demonstrations ({int(np.sum(demos.strong))} annotated), hidden {config.hidden}, "
        f"root {config.root}, {config.length_buckets} length buckets")
  print(f"{'one EG step':>24} {'1 device':>10} {'demos/s':>9}"
        + (f" {f'{num_devices} devices':>11} {'demos/s':>9} {'speed-up':>9}" if mesh is not None else ""))
  rows, seed_losses = [], {}

  def devices_row(name, value_and_grad, params, one, many):
    row = {"what": name, "devices": num_devices, "one_device_s": _median_seconds(value_and_grad, params, one)}
    text = f"{name:>24} {row['one_device_s'] * 1e3:8.1f}ms {num_demos / row['one_device_s']:9.0f}"
    if mesh is not None:
      row["all_devices_s"] = _median_seconds(value_and_grad, params, many)
      text += (f" {row['all_devices_s'] * 1e3:9.1f}ms {num_demos / row['all_devices_s']:9.0f} "
               f"{row['one_device_s'] / row['all_devices_s']:8.2f}x")
    rows.append(row)
    print(text, flush=True)

  for level in range(spec.num_levels - 1, -1, -1):
    view = level_views[level]._replace(strong=np.asarray(demos.strong))
    capacity = levelwise.level_capacity(view, level, config)

    def level_model(seed, level=level):
      seeded = dataclasses.replace(config, seed=seed)
      return objective.LevelModel(networks.make_hierarchy(spec, seeded).levels[level], networks.make_root(spec, level, seeded))

    graphdef, params, rest = nnx.split(level_model(0), nnx.Param, ...)
    loss = lambda p, b, graphdef=graphdef, rest=rest, capacity=capacity: objective.level_loss(
        nnx.merge(graphdef, p, rest), b, capacity, config.strong_weight)
    parts = views.length_buckets(view, config.length_buckets)
    one = [views.device_view(b) for b in parts]
    devices_row(f"level {level} loss (C = {capacity})", jax.jit(jax.value_and_grad(loss)), params, one,
                [views.device_view(b, mesh) for b in parts])
    if level == spec.num_levels - 1:
      seed_losses["lowest level loss"] = (loss, [nnx.split(level_model(s), nnx.Param, ...)[1]
                                                for s in range(_SEEDS.value)], one)

  capacity = joint.joint_capacity(demos, spec, config)
  graphdef, params, rest = nnx.split(networks.make_hierarchy(spec, config), nnx.Param, ...)
  loss = lambda p, b: objective.stack_loss(nnx.merge(graphdef, p, rest), b, capacity, config.strong_weight)
  one = views.demonstration_buckets(demos, config.length_buckets)
  devices_row(f"joint loss (C = {','.join(map(str, capacity))})", jax.jit(jax.value_and_grad(loss)), params, one,
              views.demonstration_buckets(demos, config.length_buckets, mesh))
  seed_losses["joint loss"] = (loss, [nnx.split(networks.make_hierarchy(spec, dataclasses.replace(config, seed=s)),
                                                nnx.Param, ...)[1] for s in range(_SEEDS.value)], one)

  seeds = _SEEDS.value
  print(f"{'gradient, one device':>24} {'1 seed':>10} {f'{seeds} in turn':>11} {'seeds/s':>8} "
        f"{f'{seeds} vmapped':>11} {'seeds/s':>8} {'vmapped vs in turn':>19}")
  for name, (loss, seed_params, one) in seed_losses.items():
    value_and_grad = jax.jit(jax.value_and_grad(loss))
    vmapped = jax.jit(jax.vmap(jax.value_and_grad(loss), in_axes=(0, None)))
    stacked = jax.tree.map(lambda *x: jnp.stack(x), *seed_params)
    row = {"what": f"{name}, {seeds} seeds", "one_seed_s": _median_seconds(value_and_grad, seed_params[0], one),
           "in_turn_s": _median_seconds(lambda ps, b: [jax.block_until_ready(value_and_grad(p, b)) for p in ps],
                                        seed_params, one),
           "vmapped_s": _median_seconds(vmapped, stacked, one)}
    rows.append(row)
    print(f"{name:>24} {row['one_seed_s'] * 1e3:8.1f}ms {row['in_turn_s'] * 1e3:9.1f}ms "
          f"{seeds / row['in_turn_s']:8.1f} {row['vmapped_s'] * 1e3:9.1f}ms {seeds / row['vmapped_s']:8.1f} "
          f"{row['in_turn_s'] / row['vmapped_s']:18.2f}x", flush=True)
  return rows


def bench_act():
  """Steps per second of `gym.act` (compiled beforehand) against the same vector environment stepped alone
  with actions drawn in advance, in the same process."""
  from php_jax.envs import gym  # gymnasium is an optional extra
  from php_jax.training import checkpoint
  if not (_POLICY.value and _ENV.value):
    cli.fail("--policy and --env are required for act")
  try:
    _, policy = checkpoint.load_policy(_POLICY.value)
    envs = gym.vector_env(gym.env_maker(_ENV.value), _NUM_ENVS.value)
  except (OSError, ValueError) as e:  # GymError and CheckpointError are ValueErrors
    cli.fail(str(e))
  gym.act(policy, envs, _NUM_ENVS.value, seed=0)  # compiles the decisions
  start = time.perf_counter()
  episodes = gym.act(policy, envs, _EPISODES.value, seed=1)
  act_seconds = time.perf_counter() - start
  steps = sum(e["steps"] for e in episodes)
  envs.action_space.seed(0)
  actions = [envs.action_space.sample() for _ in range(steps // _NUM_ENVS.value)]
  envs.reset(seed=0)
  start = time.perf_counter()
  for action in actions:
    _, _, terminated, truncated, _ = envs.step(action)
    if (done := terminated | truncated).any():
      envs.reset(options={"reset_mask": done})
  env_seconds = time.perf_counter() - start
  row = {"env": _ENV.value, "num_envs": _NUM_ENVS.value, "act_steps_per_s": steps / act_seconds,
         "env_steps_per_s": len(actions) * _NUM_ENVS.value / env_seconds,
         "success": float(np.mean([e["success"] for e in episodes]))}
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); {_ENV.value} x{_NUM_ENVS.value}")
  print(f"act: {steps} steps of {len(episodes)} episodes in {act_seconds:.2f} s = {row['act_steps_per_s']:,.0f} "
        f"steps/s; the environment alone: {row['env_steps_per_s']:,.0f} steps/s; ratio "
        f"{row['act_steps_per_s'] / row['env_steps_per_s']:.2f}")
  return [row]


BABYAI_LIKE = HierarchySpec("babyai_like", (("root",), ("go_to", "pick_up", "open", "drop")), (7,), 1004)


def babyai_like_demos(num: int, seed: int = 0) -> Demonstration:
  """num synthetic demonstrations [num, ...] of BabyAI's size (BABYAI_LIKE): 5–30 steps; each observation
  1,004 numbers, a 7 × 7 view of 20 one-hot entries per cell, a one-hot direction and 20 small integers (the
  mission's words); random actions of 7 values; half annotated with a stack of calls of 1–6 steps."""
  rng = np.random.default_rng(seed)
  lengths = rng.integers(5, 31, num)
  width = int(lengths.max())
  obs = np.zeros((num, width + 1, 1004), np.float32)
  cell = rng.integers(0, 20, (num, width + 1, 49)) + 20 * np.arange(49)
  np.put_along_axis(obs, cell, 1.0, axis=2)
  np.put_along_axis(obs, 980 + rng.integers(0, 4, (num, width + 1, 1)), 1.0, axis=2)
  obs[..., 984:] = rng.integers(0, 12, (num, width + 1, 20))
  starts = rng.random((num, width)) < 0.3  # a call starts there (and at step 0)
  starts[:, 0] = True
  call = np.cumsum(starts, axis=1) - 1
  step_in_call = np.arange(width) - np.maximum.accumulate(np.where(starts, np.arange(width), 0), axis=1)
  procedures = np.stack([np.zeros_like(call), rng.integers(0, 4, (num, width))[np.arange(num)[:, None], call]], -1)
  counters = np.stack([call, step_in_call], -1)
  pad = np.arange(width)[None, :, None] >= lengths[:, None, None]
  obs[np.arange(width + 1)[None, :] > lengths[:, None]] = 0
  actions = np.where(pad, 0, rng.integers(0, 7, (num, width, 1)))
  procedures, counters = (np.where(pad, -1, x).astype(np.int32) for x in (procedures, counters))
  return Demonstration(obs, actions.astype(np.int32), procedures, counters, lengths.astype(np.int32),
                       np.arange(num) % 2 == 0)


def bench_fast_path():
  """One EG update's time at the lowest level of BABYAI_LIKE data, today's path against each part of the fast
  one and all together: length buckets split where they pad least (instead of equal counts), a trunk per
  level (--trunk), minibatches (--batch_size). Prints ms per update, the ratio to the baseline, and each
  bucketing's padded share of the steps computed."""
  demos, spec, described = _fast_path_data()
  view = views.lowest_view(demos, spec.num_levels)
  level, hidden = spec.num_levels - 1, tuple(int(h) for h in _HIDDEN.value)
  equal_counts = views.grouped(view, np.array_split(np.argsort(view.length, kind="stable"), 4))
  fewest = views.length_buckets(view, 4)
  variants = [("today: equal-count buckets, every view", equal_counts, None, None),
              ("buckets that pad least", fewest, None, None),
              ("+ trunk 64", fewest, 64, None),
              (f"+ batch_size {_BATCH.value}", fewest, None, _BATCH.value),
              (f"all: trunk 64, batch_size {_BATCH.value}", fewest, 64, _BATCH.value)]
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); {described}, level {level}: hidden "
        f"{hidden}; padded share of the steps computed: equal counts "
        f"{views.padding_fraction(equal_counts):.3f}, fewest padded {views.padding_fraction(fewest):.3f}")
  rows, first = [], None
  for name, parts, trunk, batch in variants:
    config = TrainConfig(hidden=hidden, root="mlp", trunk=trunk, batch_size=batch,
                         strong_weight=balanced_strong_weight(demos.strong))
    model = levelwise.level_model(spec, networks.make_hierarchy(spec, config), level, config)
    buckets = [views.device_view(b) for b in parts]
    capacity = levelwise.level_capacity(view, level, config)
    loss = fitting.minibatched(lambda m, b: objective.level_loss(m, b, capacity, config.strong_weight), batch,
                               0) if batch else fitting.IterationLoss(
        lambda m, iteration, b: objective.level_loss(m, b, capacity, config.strong_weight))
    graphdef, params, rest = nnx.split(model, nnx.Param, ...)
    grad = jax.jit(jax.value_and_grad(lambda p, i: loss.fn(nnx.merge(graphdef, p, rest), i, buckets)))
    seconds = _median_seconds(grad, params, jnp.int32(0))
    first = first or seconds
    rows.append({"what": name, "ms": seconds * 1e3, "speedup": first / seconds})
    print(f"{name:>44}: {seconds * 1e3:8.1f} ms per update  ({first / seconds:.1f}× today's)")
  return rows


def _fast_path_data() -> tuple[Demonstration, HierarchySpec, str]:
  """fast_path's demonstrations, their hierarchy and a description: --demos read with --hierarchy (and, as fit
  reads them, the observation fields of --env), else --num_demos synthetic ones (`babyai_like_demos`)."""
  if not _DEMOS.value:
    num = _NUM_DEMOS.value or 300
    return babyai_like_demos(num), BABYAI_LIKE, f"{num} BabyAI-sized synthetic demonstrations"
  if not _HIERARCHY.value:
    cli.fail("fast_path with --demos needs --hierarchy")
  demos, spec = _user_demonstrations()
  return demos, spec, f"{len(demos.length)} demonstrations of {_DEMOS.value}"


def _user_demonstrations() -> tuple[Demonstration, HierarchySpec]:
  """--demos read with --hierarchy and, as fit reads them, the observation fields of --env; refused in one line
  where they cannot be read."""
  try:
    spec = demo_files.read_hierarchy(_HIERARCHY.value).spec
    if _ENV.value and spec.observation is None:
      spec = dataclasses.replace(spec, observation=_env_fields(_ENV.value))
    return demo_files.read_demonstrations(_DEMOS.value, spec)
  except demo_files.DemoFileError as e:
    cli.fail(str(e))
  except ValueError as e:  # the environment's fields beside the hierarchy file's "observes"
    cli.fail(f"--env={_ENV.value}: {e}" if _ENV.value else str(e))


def _env_fields(env_id: str):
  """The observation fields of env_id (`gym.env_observation_fields`); refused in one line where it cannot be
  made."""
  from php_jax.envs import gym  # gymnasium is an optional extra
  try:
    return gym.env_observation_fields(env_id)
  except gym.GymError as e:
    cli.fail(f"--env={env_id}: {e}")


def _size(path: str) -> int:
  return sum(os.path.getsize(os.path.join(path, n)) for n in os.listdir(path)) if os.path.isdir(path) else (
      os.path.getsize(path))


def bench_demo_files():
  """Writing and reading --num_demos synthetic demonstrations (babyai_like_demos) as JSON lines (the
  baseline) and as a binary set, each the median of 3 rounds: bytes and seconds, and the binary's ratios."""
  num = _NUM_DEMOS.value or 1000
  batch = babyai_like_demos(num)
  print(f"{num} synthetic demonstrations of BabyAI's size: {int(batch.length.sum())} steps, 1,004 numbers an "
        f"observation, {int(batch.strong.sum())} annotated; JSON lines vs a binary set of {shards.SHARD_SIZE} a shard")
  rows, read = [], {}
  with tempfile.TemporaryDirectory() as folder:
    for name, path in (("JSON lines", "demos.jsonl"), ("binary", "demos" + shards.SUFFIX)):
      path = os.path.join(folder, path)
      write_s = statistics.median(_seconds(demo_files.write_demonstrations, path, batch, batch.strong)
                                  for _ in range(3))
      read_s = statistics.median(_seconds(demo_files.read_demonstrations, path, BABYAI_LIKE) for _ in range(3))
      read[name], _ = demo_files.read_demonstrations(path, BABYAI_LIKE)
      rows.append({"format": name, "bytes": _size(path), "write_s": write_s, "read_s": read_s})
  assert all(np.array_equal(a, b) for a, b in zip(*read.values())), "the two formats read to different arrays"
  for row in rows:
    print(f"{row['format']:>11}: {row['bytes']:13,} bytes, written in {row['write_s']:6.2f} s, read in "
          f"{row['read_s']:6.2f} s")
  lines, binary = rows
  print(f"binary / JSON: size {binary['bytes'] / lines['bytes']:.4f} (1/{lines['bytes'] / binary['bytes']:.0f}), "
        f"write time {binary['write_s'] / lines['write_s']:.3f}, read time {binary['read_s'] / lines['read_s']:.3f}; "
        "both read to the same arrays")
  return rows


def bench_many_demos():
  """experiments.fit with its defaults and --iterations on each --copies count of copies of --demos (a binary
  set written to a temporary folder), each in a process of its own: the process's peak resident memory, the
  seconds per update and demonstration steps per second from its first evaluation to its last (the held-out
  replays at each evaluation included), its wall time, and the ratios to the first fit's."""
  if not (_DEMOS.value and _HIERARCHY.value):
    cli.fail("many_demos needs --demos and --hierarchy")
  if _ITERATIONS.value < 2 * TrainConfig().eval_every:
    cli.fail(f"many_demos times from a fit's first evaluation to its last: --iterations must be at least "
             f"{2 * TrainConfig().eval_every}")
  if not all(c.isdigit() and int(c) > 0 for c in _COPIES.value):
    cli.fail(f"--copies must list positive integers; got {','.join(_COPIES.value)}")
  batch, _ = _user_demonstrations()
  one, mean_length = list(shards.unpadded(batch, batch.strong)), float(np.mean(batch.length))
  print(f"device: {jax.devices()[0].device_kind} ({jax.default_backend()}); {len(one)} demonstrations of "
        f"{_DEMOS.value} ({mean_length:.1f} steps on average), copied; fit --iterations={_ITERATIONS.value}")
  rows = []
  with tempfile.TemporaryDirectory() as folder:
    for copies in (int(c) for c in _COPIES.value):
      path, workdir = os.path.join(folder, f"copies{copies}{shards.SUFFIX}"), os.path.join(folder, f"fit{copies}")
      shards.write_shards(path, itertools.chain.from_iterable(itertools.repeat(one, copies)))
      command = [sys.executable, "-m", "experiments.fit", f"--demos={path}", f"--hierarchy={_HIERARCHY.value}",
                 f"--workdir={workdir}", "--seed=1", f"--iterations={_ITERATIONS.value}",
                 *([f"--env={_ENV.value}"] if _ENV.value else [])]
      with open(os.path.join(folder, "fit.err"), "w") as err:
        start = time.perf_counter()
        process = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=err)
        _, status, usage = os.wait4(process.pid, 0)  # the fit's own peak memory, which Popen.wait does not give
        process.returncode, wall = os.waitstatus_to_exitcode(status), time.perf_counter() - start  # reaped here
      if process.returncode:
        with open(err.name) as f:
          raise RuntimeError(f"{' '.join(command)} ended with status {process.returncode}: {f.read()[-2000:]}")
      with open(os.path.join(workdir, "results.json")) as f:
        results = json.load(f)
      with open(os.path.join(workdir, "metrics.jsonl")) as f:
        timed = [row for row in map(json.loads, f) if "iteration" in row and "seconds" in row]
      updates, seconds = timed[-1]["iteration"] - timed[0]["iteration"], timed[-1]["seconds"] - timed[0]["seconds"]
      batch_size = results["config"]["batch_size"] or results["num_demos"]
      row = {"demonstrations": len(one) * copies, "batch_size": batch_size, "peak_gb": usage.ru_maxrss / 2**20,
             "s_per_update": seconds / updates, "steps_per_s": updates * batch_size * mean_length / seconds,
             "wall_s": wall}
      rows.append(row)
      print(f"{row['demonstrations']:>9,} demonstrations (batch {batch_size}): peak memory {row['peak_gb']:5.2f} GB "
            f"({row['peak_gb'] / rows[0]['peak_gb']:.2f}× the first), {row['s_per_update']:.3f} s per update "
            f"({row['s_per_update'] / rows[0]['s_per_update']:.2f}×), {row['steps_per_s']:,.0f} steps/s, wall "
            f"{wall:.0f} s")
  return rows


def _seconds(fn, *args) -> float:
  start = time.perf_counter()
  fn(*args)
  return time.perf_counter() - start


def _task():
  if not _TASK.value:
    cli.fail("--task is required for rollout, train_step and scaling")
  try:
    return tasks.get(_TASK.value)
  except ValueError as e:
    cli.fail(f"--task: {e}")


def main(argv):
  commands = {"estep": bench_estep, "estep_grad": bench_estep_grad, "rollout": bench_rollout,
              "train_step": bench_train_step, "scaling": bench_scaling, "act": bench_act,
              "demo_files": bench_demo_files, "fast_path": bench_fast_path,
              "many_demos": bench_many_demos}
  if len(argv) != 2 or argv[1] not in commands:
    cli.fail(f"usage: python -m experiments.benchmark {{{'|'.join(commands)}}} [--flags]")
  try:
    cli.check_outputs({"out": _OUT.value}, {"demos": _DEMOS.value, "hierarchy": _HIERARCHY.value})
  except ValueError as e:
    cli.fail(str(e))
  try:  # Ctrl-C unwinds, so that the temporary folders (many_demos' copies) are removed
    rows = commands[argv[1]]()
  except KeyboardInterrupt:
    print("interrupted: the benchmark stopped before its end; --out was not written", file=sys.stderr)
    sys.exit(130)
  if _OUT.value:
    files.write_atomically(_OUT.value, json.dumps(rows, indent=1).encode())


if __name__ == "__main__":
  app.run(main, flags_parser=cli.parse_flags)
