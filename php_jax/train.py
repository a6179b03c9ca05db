"""Expectation–Gradient training of PHPs (paper §4.2, DESIGN.md §4): one level at a time, lowest first.

Level i's loss on a batch of its views is −(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N, each term the
lattice's exact log-likelihood (strong views through `annotate`). Below the root level, a root network (MLP
or LSTM over the view's observations) stands in for the untrained levels above; the root level is the
lattice's top-level mode (one procedure, called once). An optional per-level call penalty λ is a prior on
the latent call sequence: the root's log η_⊥ drops by λ at every push, so weak views' posteriors favour fewer,
longer calls (a strong view's log-likelihood drops by λ per call, a constant). After a level is trained, its
weak views are decoded (Viterbi, per-step max-marginal, or a posterior sample) into the view of the level
above.
"""
from __future__ import annotations

import dataclasses
import itertools
import json
import os
import time
from typing import Callable

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx, serialization

from php_jax import checkpoint, fitting, lattice, views
from php_jax.demos import UNKNOWN, Demonstration
from php_jax.demos import validate as validate_demos
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, PHPLevel, RootLSTM, RootMLP

DECODERS = ("sample", "viterbi", "max_marginal")


@dataclasses.dataclass(frozen=True)
class TrainConfig:
  """Hyper-parameters of level-wise EG training (defaults follow the paper where it says)."""
  iterations: int = 2000            # per level, as in the paper
  learning_rate: float = 3e-3
  hidden: tuple[int, ...] = (64, 64)
  root: str = "lstm"                # network standing in for untrained levels: "lstm" or "mlp"
  root_hidden: int = 64
  tau_in_termination: tuple[bool, ...] | None = None  # per level; None: all True
  strong_weight: float | None = None  # weight on strongly supervised demonstrations' loss; None: balanced
  root_strong_weight: float | None = None  # the root level's: its weak views have no latent choice; None: the same
  strong_warmup: int = 0            # below the root, iterations on the strong views alone before those on all
  call_penalty: tuple[float, ...] | None = None  # per level (root first), log-prior cost of each call; None: 0
  decode: str = "sample"            # how weak views are decoded for the level above (the paper sampled)
  capacity: int = 8                 # counter capacity C below the root level when nothing is annotated
  eval_every: int = 100             # logging, checkpoint and root-snapshot interval
  snapshot: str = "latest"          # root snapshot among the equally best-validated: "latest" or "earliest"
  length_buckets: int = 4           # views are batched by length into this many buckets
  seed: int = 0


class LevelModel(nnx.Module):
  """What one level trains: its PHP networks, and a root network unless it is the root level. call_penalty
  (not trained) is subtracted from the root network's log η_⊥ at every push (`lattice_inputs`)."""

  def __init__(self, php: PHPLevel, root: nnx.Module | None, call_penalty: float = 0.0):
    self.php = php
    self.root = root
    self.call_penalty = call_penalty


def lattice_inputs(model: LevelModel, observations, actions, procedures, counters, length, capacity: int):
  """One view → the lattice's inputs, annotated where procedures/counters are known.

  observations [T+1, D], actions [T, F], procedures/counters [T] (UNKNOWN = −1), length [] →
  (log_root [T, K], log_op, log_stop, log_cont [T, K, C]).
  """
  tau = jnp.arange(capacity, dtype=jnp.float32)
  log_op = model.php.log_op(observations[:-1], tau, actions)
  z = model.php.termination_logits(observations[1:], tau)
  log_stop, log_cont = jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)
  if model.root is None:  # the root level: one procedure, called once
    log_root = jnp.zeros(log_op.shape[:2], log_op.dtype)
    log_stop = lattice.top_level(log_stop, length)
  else:
    log_root = model.root(observations[:-1]) - model.call_penalty
  return log_root, lattice.annotate(log_op, procedures, counters), log_stop, log_cont


def view_log_likelihoods(model: LevelModel, batch: views.LevelView, capacity: int) -> jax.Array:
  """[B] log P(ζ, ξ) for annotated views, log P(ξ) for the others."""
  def one(obs, act, proc, tau, n):
    return lattice.forward_backward(*lattice_inputs(model, obs, act, proc, tau, n, capacity),
                                    length=n).log_likelihood
  return jax.vmap(one)(batch.observations, batch.actions, batch.procedures, batch.counters, batch.length)


def level_loss(model: LevelModel, buckets: list[views.LevelView], capacity: int, strong_weight: float) -> jax.Array:
  """−(w_strong Σ_strong log P(ζ, ξ) + Σ_weak log P(ξ)) / N over the views of every length bucket."""
  total, count = 0.0, 0
  for batch in buckets:
    weights = jnp.where(batch.strong, strong_weight, 1.0)
    total = total - jnp.sum(weights * view_log_likelihoods(model, batch, capacity))
    count += batch.length.shape[0]
  return total / count


def length_buckets(view: views.LevelView, num_buckets: int) -> list[views.LevelView]:
  """The views sorted by length into up to num_buckets groups of similar size, each trimmed to its longest
  view: the networks run on far fewer padding cells than in one batch padded to the longest view."""
  order = np.argsort(view.length, kind="stable")
  buckets = []
  for group in np.array_split(order, min(num_buckets, len(order))):
    width = int(view.length[group].max())
    buckets.append(views.LevelView(
        view.observations[group, :width + 1], view.actions[group, :width], view.procedures[group, :width],
        view.counters[group, :width], view.length[group], view.times[group, :width], view.strong[group]))
  return buckets


def device_view(view: views.LevelView) -> views.LevelView:
  """The view as device arrays, with annotations only on strong demonstrations."""
  strong = view.strong[:, None]
  return views.LevelView(
      observations=jnp.asarray(view.observations), actions=jnp.asarray(view.actions),
      procedures=jnp.asarray(np.where(strong, view.procedures, UNKNOWN)),
      counters=jnp.asarray(np.where(strong, view.counters, UNKNOWN)),
      length=jnp.asarray(view.length), times=jnp.asarray(view.times), strong=jnp.asarray(view.strong))


def decode(model: LevelModel, view: views.LevelView, capacity: int, method: str, key: jax.Array):
  """Each view's most likely / sampled frames at this level: (procedures, counters) [B, T] numpy."""
  batch = device_view(view)

  def one(obs, act, proc, tau, n, k):
    inputs = lattice_inputs(model, obs, act, proc, tau, n, capacity)
    if method == "viterbi":
      return lattice.viterbi(*inputs, length=n)
    if method == "sample":
      return lattice.sample_posterior(k, *inputs, length=n)
    return lattice.max_marginal_path(lattice.forward_backward(*inputs, length=n), length=n)

  keys = jax.random.split(key, view.length.shape[0])
  paths = jax.jit(jax.vmap(one))(batch.observations, batch.actions, batch.procedures, batch.counters,
                                 batch.length, keys)
  return np.asarray(paths.procedure), np.asarray(paths.counter)


def train_level(model: LevelModel, view: views.LevelView, capacity: int, config: TrainConfig,
                on_eval: Callable[[int, float], float | None] | None = None,
                log: Callable[[dict], None] = print, resume: fitting.Progress | None = None,
                save: Callable[[fitting.Progress], None] | None = None) -> fitting.Progress:
  """Full-batch Adam on one level's EG loss over its views in length buckets (`fitting.fit`: snapshots,
  saving, resuming). Updates `model` in place. The root level's strong weight is config.root_strong_weight
  when set.

  Below the root level, with config.strong_warmup = W (and both kinds of view present), iterations 1..W fit
  the strong views alone and W+1..W+config.iterations all of them: the weak views' posteriors then start
  from networks that follow the annotated hierarchy instead of from random ones (paper §6: weak views can
  pull the fit towards another hierarchy). The root level's weak views have no latent choice (one procedure,
  τ = step), so it has no warm-up."""
  is_root = model.root is None
  strong_weight = config.root_strong_weight if is_root and config.root_strong_weight is not None else (
      config.strong_weight)

  def fit(part: views.LevelView, iterations: int, progress: fitting.Progress | None) -> fitting.Progress:
    buckets = [device_view(b) for b in length_buckets(part, config.length_buckets)]
    return fitting.fit(model, lambda m: level_loss(m, buckets, capacity, strong_weight), iterations,
                       config.learning_rate, config.eval_every, on_eval, log, progress, save, config.snapshot)

  warmup = config.strong_warmup if not is_root and 0 < view.strong.sum() < len(view.strong) else 0
  if warmup and (resume is None or resume.iteration < warmup):
    resume = fit(views.select(view, view.strong), warmup, resume)
  return fit(view, warmup + config.iterations, resume)


def level_capacity(view: views.LevelView, level: int, config: TrainConfig) -> int:
  """The root level needs its whole view; below, the longest annotated call (the cells the networks are
  evaluated on scale with C), or config.capacity when nothing is annotated."""
  if level == 0:
    return int(view.length.max())
  annotated = view.counters[view.strong][view.counters[view.strong] >= 0]
  return int(annotated.max()) + 1 if annotated.size else config.capacity


def weak_with_stack(demos: Demonstration, view: views.LevelView, level: int) -> list[int]:
  """The weak demonstrations whose supervisor's stack at `level` is known on every elementary step: those
  a decoding can be checked against."""
  true_procs = np.asarray(demos.procedures)[..., level]
  return [int(b) for b in np.flatnonzero(~view.strong) if np.all(true_procs[b, :int(demos.length[b])] != UNKNOWN)]


def agreement_counts(demos: Demonstration, view: views.LevelView, level: int, procedures, counters):
  """[K, K] counts of weak demonstrations' elementary steps decoded as procedure i at `level` whose
  supervisor's procedure is j, with equal counters (None if no weak demonstration carries the supervisor's
  stack), and the number of such steps."""
  true_procs, true_taus = np.asarray(demos.procedures), np.asarray(demos.counters)
  num_procs = int(max(true_procs[..., level].max(), np.max(procedures))) + 1
  counts, total = np.zeros((num_procs, num_procs), np.int64), 0
  for b in weak_with_stack(demos, view, level):
    bounds = list(view.times[b, :view.length[b]]) + [int(demos.length[b])]
    for k in range(view.length[b]):
      steps = slice(bounds[k], bounds[k + 1])
      same_tau = true_taus[b, steps, level] == counters[b, k]
      np.add.at(counts[procedures[b, k]], true_procs[b, steps, level][same_tau], 1)
      total += bounds[k + 1] - bounds[k]
  return (counts, total) if total else (None, 0)


def agreement(demos: Demonstration, view: views.LevelView, level: int, procedures, counters) -> float | None:
  """Fraction of weak demonstrations' elementary steps whose decoded (procedure, counter) at `level` equals
  the supervisor's (None if no weak demonstration carries the supervisor's stack)."""
  return _exact_fraction(*agreement_counts(demos, view, level, procedures, counters))


def relabelled_agreement(demos: Demonstration, view: views.LevelView, level: int, procedures,
                         counters) -> float | None:
  """agreement() under the renaming of decoded procedures that maximises it: how close the segmentation is
  to the supervisor's when the procedures' ids are arbitrary (weak-only training). Brute force over the
  K! renamings, so None (not measured) above K = 8, as when no weak demonstration carries the stack."""
  return _relabelled_fraction(*agreement_counts(demos, view, level, procedures, counters))


def _exact_fraction(counts, total: int) -> float | None:
  return None if counts is None else float(np.trace(counts) / total)


def _relabelled_fraction(counts, total: int) -> float | None:
  num_procs = 0 if counts is None else len(counts)
  if not 0 < num_procs <= 8:
    return None
  rows = np.arange(num_procs)
  best = max(counts[rows, list(perm)].sum() for perm in itertools.permutations(range(num_procs)))
  return float(best / total)


def balanced_strong_weight(strong) -> float:
  """num_weak / num_strong (at least 1): strong and weak demonstrations then weigh the same in the loss, so
  a few annotated ones are not outvoted by many weak ones pulling towards another hierarchy (paper §5.2)."""
  num_strong = int(np.sum(strong))
  return max(1.0, (len(strong) - num_strong) / num_strong) if num_strong else 1.0


def make_hierarchy(spec: HierarchySpec, config: TrainConfig) -> PHPHierarchy:
  return PHPHierarchy(spec, hidden=config.hidden, tau_in_termination=config.tau_in_termination,
                      rngs=nnx.Rngs(config.seed))


def make_root(spec: HierarchySpec, level: int, config: TrainConfig) -> nnx.Module | None:
  """The root network standing in for the untrained levels above `level` (None for the root level)."""
  if level == 0:
    return None
  rngs = nnx.Rngs(config.seed + 1000 + level)
  if config.root == "lstm":
    return RootLSTM(spec.obs_dim, spec.num_procs(level), config.root_hidden, rngs=rngs)
  return RootMLP(spec.obs_dim, spec.num_procs(level), (config.root_hidden,), rngs=rngs)


def _leaves(tree) -> dict:
  return {str(i): np.asarray(x) for i, x in enumerate(jax.tree.leaves(tree))}


def _unflatten(template, leaves: dict):
  return jax.tree.unflatten(jax.tree.structure(template), [jnp.asarray(leaves[str(i)]) for i in range(len(leaves))])


def train_hierarchy(spec: HierarchySpec, demos: Demonstration, config: TrainConfig,
                    validate: Callable[[PHPHierarchy], float] | None = None,
                    log: Callable[[dict], None] = print,
                    checkpoint_path: str | None = None) -> tuple[PHPHierarchy, dict]:
  """Trains every level from the lowest to the root. validate(hierarchy) → validation accuracy, used to pick
  the root level's snapshot. With checkpoint_path, progress is saved there atomically every eval_every
  iterations and an interrupted run resumes from it, ending with the same result as an uninterrupted one.
  Returns the hierarchy and a report (per level: losses, capacity, decoding agreement with the supervisor on
  weak demonstrations, wall time)."""
  if config.decode not in DECODERS:
    raise ValueError(f"decode must be one of {DECODERS}; got {config.decode!r}")
  if config.call_penalty is not None and (len(config.call_penalty) != spec.num_levels or config.call_penalty[0]):
    raise ValueError(f"call_penalty needs one value per level, root first, the root's 0 (it has no stand-in root); "
                     f"got {config.call_penalty} for {spec.num_levels} levels")
  validate_demos(demos, spec)  # malformed annotations are refused, naming the demonstration and step
  if config.strong_weight is None:
    config = dataclasses.replace(config, strong_weight=balanced_strong_weight(np.asarray(demos.strong)))
  hierarchy = make_hierarchy(spec, config)
  saved = _read_checkpoint(checkpoint_path)
  report, decoded = {}, {}
  if saved is not None:
    meta, state = saved
    nnx.update(hierarchy, _unflatten(nnx.state(hierarchy, nnx.Param), state["hierarchy"]))
    report = {int(k): v for k, v in meta["report"].items()}
    decoded = _decoded(state)
    log({"resumed": True, "level": meta["level"], "iteration": meta["iteration"]})
  view = views.lowest_view(demos, spec.num_levels)
  for level in range(spec.num_levels - 1, -1, -1):
    start = time.time()
    capacity = level_capacity(view, level, config)
    if level not in report:
      model = LevelModel(hierarchy.levels[level], make_root(spec, level, config),
                         config.call_penalty[level] if config.call_penalty else 0.0)
      resume = _progress_from(saved, model) if saved is not None and saved[0]["level"] == level else None
      on_eval = (lambda it, loss: validate(hierarchy)) if (level == 0 and validate) else None
      log({"level": level, "capacity": capacity, "view_length": int(view.length.max())})

      def save(progress, level=level):
        _write_checkpoint(checkpoint_path, hierarchy, level, progress, report, decoded)

      progress = train_level(model, view, capacity, config, on_eval,
                             log=lambda row, level=level: log({"level": level, **row}), resume=resume,
                             save=save if checkpoint_path else None)
      entry = {"capacity": capacity, "losses": progress.losses, "best_iteration": progress.best_iteration,
               "validation": progress.best_score}
      if level > 0:
        key = jax.random.fold_in(jax.random.key(config.seed), level)
        procs, taus = decode(model, view, capacity, config.decode, key)
        decoded[level] = (np.where(view.strong[:, None], view.procedures, procs),
                          np.where(view.strong[:, None], view.counters, taus))
        counts = agreement_counts(demos, view, level, *decoded[level])  # counted once for both measures
        entry["decoding_agreement"] = _exact_fraction(*counts)
        entry["relabelled_agreement"] = _relabelled_fraction(*counts)
      entry["seconds"] = time.time() - start
      report[level] = entry
      if checkpoint_path:  # the level is complete: its result survives a restart
        _write_checkpoint(checkpoint_path, hierarchy, level - 1, None, report, decoded)
    if level > 0:
      view = views.view_above(demos, view, level, *decoded[level])
  return hierarchy, report


def _progress_from(saved, model: LevelModel) -> fitting.Progress:
  """The saved in-progress level's Progress, shaped like a fresh optimizer for `model`."""
  meta, state = saved
  params = nnx.state(model, nnx.Param)
  template = (params, optax.adam(0.0).init(params), params)
  restored = _unflatten(template, state["progress"])
  p = meta["progress"]
  return fitting.Progress(p["iteration"], *restored, p["best_iteration"], p["best_score"],
                       [list(x) for x in p["losses"]])


def _write_checkpoint(path, hierarchy, level, progress: fitting.Progress | None, report, decoded) -> None:
  """One file: the hierarchy's parameters, the level in progress (or the next level, not started), decodings."""
  meta = {"level": level, "iteration": progress.iteration if progress else 0, "report": report,
          "progress": None if progress is None else {
              "iteration": progress.iteration, "best_iteration": progress.best_iteration,
              "best_score": progress.best_score, "losses": progress.losses}}
  state = {"hierarchy": _leaves(nnx.state(hierarchy, nnx.Param)),
           "progress": {} if progress is None else _leaves((progress.params, progress.opt_state,
                                                              progress.best_params)),
           "decoded": {str(k): {"procedures": v[0], "counters": v[1]} for k, v in decoded.items()},
           "meta": json.dumps(meta)}
  checkpoint.write_atomically(path, serialization.msgpack_serialize(state))


def read_decoded(path: str) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  """The (procedures, counters) [B, T] per trained level > 0 saved in a training checkpoint: each level's
  view of every demonstration, annotated where strong and decoded where weak."""
  saved = _read_checkpoint(path)
  if saved is None:
    raise FileNotFoundError(f"no training checkpoint at {path}")
  return _decoded(saved[1])


def _decoded(state) -> dict[int, tuple[np.ndarray, np.ndarray]]:
  return {int(k): (np.asarray(v["procedures"]), np.asarray(v["counters"])) for k, v in state["decoded"].items()}


def _read_checkpoint(path):
  """(meta, state) from a checkpoint file, or None if there is none."""
  if not path or not os.path.isfile(path):
    return None
  with open(path, "rb") as f:
    state = serialization.msgpack_restore(f.read())
  meta = json.loads(state["meta"])
  if meta["progress"] is None:  # saved between levels: the next level starts fresh
    meta["level"] = None
  return meta, state
