"""Adam, full-batch or on minibatches of demonstrations, with the project's snapshot rule and resumable
progress: the loop that the PHP levels (php_jax.training.levelwise), joint training (php_jax.training.joint)
and the flat baselines (php_jax.flat) train with (`fit`), and the same loop and update step for
several seeds' models at once, vmapped (`fit_seeds`, for php_jax.training.levelwise.train_seeds)."""
from __future__ import annotations

import functools
import time
from typing import Any, Callable, NamedTuple, Sequence

import jax
import jax.numpy as jnp
import numpy as np
import optax
from flax import nnx
from jax.sharding import Mesh

from php_jax import sharding

SNAPSHOT_RULES = ("earliest", "latest")  # which of the equally best-validated snapshots fit keeps


class Progress(NamedTuple):
  """Where a fit stands, for checkpoints: after `iteration` updates."""
  iteration: int
  params: Any
  opt_state: Any
  best_params: Any          # the kept snapshot (the current params until a validation score exists)
  best_iteration: int | None
  best_score: float | None
  losses: list


class Schedule(NamedTuple):
  """How a fit runs: `iterations` Adam updates at `learning_rate`; every `eval_every` iterations and at the
  end, an evaluation (a validation score, a logged row, a save); `snapshot`, which of the equally
  best-validated snapshots is kept (SNAPSHOT_RULES); a save also whenever `save_seconds` have passed;
  `weight_decay`, AdamW's decoupled decay of every parameter (0: plain Adam); `batch_size`, demonstrations
  per update (`minibatched`; None or 0: all of them), drawn by `batch_seed`."""
  iterations: int
  learning_rate: float
  eval_every: int
  snapshot: str = "latest"
  save_seconds: float = 30.0
  weight_decay: float = 0.0
  batch_size: int | None = None
  batch_seed: int = 0


class Hooks(NamedTuple):
  """What a fit calls at each evaluation. For `fit`: on_eval(iteration, loss) → a validation score or None,
  log(row), save(progress). For `fit_seeds`, per model s: on_eval(iteration, losses) → [score or None],
  log(s, row), save([progress])."""
  on_eval: Callable | None = None
  log: Callable = print
  save: Callable | None = None

  def for_models(self) -> Hooks:
    """`fit`'s hooks in `fit_seeds`' form, for one model."""
    on_eval, log, save = self
    return Hooks((lambda iteration, losses: [on_eval(iteration, losses[0])]) if on_eval else None,
                 lambda s, row: log(row), (lambda progresses: save(progresses[0])) if save else None)

  def of_first_model(self) -> Hooks:
    """`fit_seeds`' hooks in `fit`'s form, for its first model alone."""
    on_eval, log, save = self
    return Hooks((lambda iteration, loss: on_eval(iteration, [loss])[0]) if on_eval else None,
                 lambda row: log(0, row), (lambda progress: save([progress])) if save else None)


class IterationLoss(NamedTuple):
  """A loss that changes over a fit (one compiled update all the same): `fit` calls fn(model, iteration,
  *args), iteration [] int32 the number of updates made before this one (0 at the first)."""
  fn: Callable[..., jax.Array]


def minibatched(loss_fn: Callable[..., jax.Array] | IterationLoss, batch_size: int, seed: int) -> IterationLoss:
  """loss_fn on a minibatch of its first argument, a list of buckets (pytrees whose leaves lead with the
  bucket's B_b rows), drawn inside the compiled update (`batch_rows`). The loss's own normalisation (a mean
  over the rows it is given) then makes it an estimate of the full loss, and its gradient of the full
  gradient."""
  takes_iteration = isinstance(loss_fn, IterationLoss)
  fn = loss_fn.fn if takes_iteration else loss_fn

  def loss(model, iteration, buckets, *rest):
    rows = batch_rows([_rows(bucket) for bucket in buckets], batch_size, seed, iteration)
    drawn = [jax.tree.map(lambda x, r=r: x[r], bucket) for bucket, r in zip(buckets, rows)]
    return fn(model, *((iteration,) if takes_iteration else ()), drawn, *rest)
  return IterationLoss(loss)


def batch_rows(sizes: Sequence[int], batch_size: int, seed: int, iteration) -> list[jax.Array]:
  """The rows an update draws from buckets of B_b = sizes[b] rows: round(batch_size · B_b / Σ B) (at least 1)
  of every bucket, without replacement, afresh from seed and `iteration` ([] int, the number of updates made
  before it), so that a resumed fit draws what an uninterrupted one would. [count_b] int32 per bucket."""
  key = jax.random.fold_in(jax.random.key(seed), iteration)
  return [jax.random.choice(jax.random.fold_in(key, index), size,
                            (min(size, max(1, round(batch_size * size / sum(sizes)))),), replace=False)
          for index, size in enumerate(sizes)]


def host_minibatches(buckets: list, batch_size: int, seed: int) -> Callable[[int], list]:
  """draw(iteration) → the minibatch of buckets (pytrees of arrays [B_b, ...], kept as host arrays) that update
  `iteration` (the number made before it) takes: the rows `minibatched` would draw (`batch_rows`, computed on
  the CPU, so a GPU is not waited for), gathered on the host. Only the drawn rows then go to the device."""
  buckets = [jax.tree.map(np.asarray, bucket) for bucket in buckets]
  try:
    cpu = jax.devices("cpu")[0]
  except RuntimeError:  # JAX_PLATFORMS without cpu: the default device draws them
    cpu = jax.devices()[0]
  rows = jax.jit(functools.partial(batch_rows, [_rows(bucket) for bucket in buckets], batch_size, seed))

  def draw(iteration: int) -> list:
    with jax.default_device(cpu):
      drawn = [np.asarray(r) for r in rows(np.int32(iteration))]
    return [jax.tree.map(lambda x, r=r: x[r], bucket) for bucket, r in zip(buckets, drawn)]
  return draw


def _rows(bucket: Any, axis: int = 0) -> int:
  return jax.tree.leaves(bucket)[0].shape[axis]


def _per_batch(loss_fn, schedule: Schedule, args: tuple, axis: int = 0):
  """loss_fn, or where schedule.batch_size is below the rows of args[0]'s buckets (along their leaves' axis
  `axis`), `minibatched`."""
  if not schedule.batch_size or not args:
    return loss_fn
  rows = sum(_rows(bucket, axis) for bucket in args[0])
  return loss_fn if schedule.batch_size >= rows else minibatched(loss_fn, schedule.batch_size, schedule.batch_seed)


def fit(model: nnx.Module, loss_fn: Callable[..., jax.Array] | IterationLoss, schedule: Schedule,
        hooks: Hooks = Hooks(), resume: Progress | None = None, args: tuple = (),
        mesh: Mesh | None = None) -> Progress:
  """Adam on loss_fn(model, *args) [] (an IterationLoss: also given the iteration), on every demonstration
  or, with schedule.batch_size, on a minibatch of args[0]'s buckets (`batch_rows`). Updates `model` in
  place to the kept snapshot.

  args (the data) follow the model into loss_fn. Without a mesh, give host arrays: a full batch becomes
  constants of the compiled update, and minibatches are drawn on the host (`host_minibatches`), so the device
  holds one minibatch at a time, never the whole set. With a mesh, give arrays split over it (then the
  parameters and optimizer state are replicated on the mesh, minibatches are drawn inside the update
  (`minibatched`), and the model gets its parameters back as arrays of the default device).

  At each evaluation (`Schedule`): hooks.on_eval(iteration, loss) may return a validation score (the
  snapshot with the highest score is kept, the latest or the earliest among equals as schedule.snapshot
  says; without scores, the final iterate), then the row is logged and hooks.save(progress) called. resume
  continues from a saved Progress, to the same result as an uninterrupted fit.
  """
  graphdef, params, rest = nnx.split(model, nnx.Param, ...)
  optimizer = _optimizer(schedule)
  progress = resume if resume is not None else Progress(0, params, optimizer.init(params), params, None, None,
                                                        [])
  per_batch = _per_batch(loss_fn, schedule, args)
  drawn_on_host = mesh is None and per_batch is not loss_fn  # the device holds one minibatch at a time
  step = _adam_step(graphdef, loss_fn if drawn_on_host else per_batch, optimizer)
  on_data = jax.jit(lambda params, opt_state, args: step(params, opt_state, rest, args))
  if drawn_on_host:
    draw = host_minibatches(args[0], schedule.batch_size, schedule.batch_seed)
    others = jax.tree.map(jnp.asarray, args[1:])

    def update(params, opt_state, iteration):
      return on_data(params, opt_state, (draw(iteration - 1), *others))
  elif mesh is None:  # the whole batch as constants, folded into the program by XLA
    constants = jax.tree.map(jnp.asarray, args)
    update = _ignoring_iteration(jax.jit(lambda params, opt_state: step(params, opt_state, rest, constants)))
  else:  # as arguments, split over the mesh by the caller: a constant would sit whole on one device
    update = _ignoring_iteration(functools.partial(on_data, args=args))
  [progress] = _iterate(_Loop(update, [model], mesh, lambda tree, s: tree),
                        sharding.replicate((progress.params, progress.opt_state), mesh), [progress], schedule,
                        hooks.for_models())
  return progress


def fit_seeds(models: Sequence[nnx.Module], loss_fn: Callable[..., jax.Array], schedule: Schedule,
              hooks: Hooks = Hooks(), resume: list[Progress] | None = None, args: tuple = (),
              mesh: Mesh | None = None, batch_seeds: Sequence[int] | None = None) -> list[Progress]:
  """`fit` for S independent models of one architecture (one per seed), as one vmapped program: model s is
  trained on loss_fn(models[s], *args_s) [], where args' leaves are stacked along a leading S axis, and keeps
  its own snapshot. hooks take every model's losses, scores and progress (`Hooks`); resume takes one Progress
  per model (each as `fit` makes it). With a mesh (args placed on it by the caller), the parameters and
  optimizer states are replicated on it. With schedule.batch_size, model s draws its minibatches from
  batch_seeds[s] (default: schedule.batch_seed), as its own `fit` would. Updates each model in place to its
  kept snapshot; returns the Progress of each."""
  splits = [nnx.split(model, nnx.Param, ...) for model in models]
  graphdef, rest = splits[0][0], _stack([r for _, _, r in splits])
  optimizer = _optimizer(schedule)
  progress = resume if resume is not None else [Progress(0, p, optimizer.init(p), p, None, None, [])
                                                for _, p, _ in splits]
  if _per_batch(loss_fn, schedule, args, axis=1) is not loss_fn:  # each model's seed, an argument of its own
    seeds = batch_seeds or [schedule.batch_seed] * len(models)
    args = (*args, sharding.replicate(jnp.asarray(seeds, jnp.int32), mesh))
    each = loss_fn
    loss_fn = IterationLoss(lambda model, iteration, *rest: minibatched(each, schedule.batch_size, rest[-1]).fn(
        model, iteration, *rest[:-1]))
  update = jax.jit(jax.vmap(_adam_step(graphdef, loss_fn, optimizer)))
  state = sharding.replicate((_stack([p.params for p in progress]), _stack([p.opt_state for p in progress])), mesh)
  rest = sharding.replicate(rest, mesh)
  return _iterate(_Loop(_ignoring_iteration(lambda params, opt_state: update(params, opt_state, rest, args)), models,
                        mesh, _unstack),
                  state, progress, schedule, hooks)


def _optimizer(schedule: Schedule) -> optax.GradientTransformation:
  if schedule.snapshot not in SNAPSHOT_RULES:
    raise ValueError(f"snapshot must be one of {SNAPSHOT_RULES}; got {schedule.snapshot!r}")
  if schedule.weight_decay:
    return optax.adamw(schedule.learning_rate, weight_decay=schedule.weight_decay)
  return optax.adam(schedule.learning_rate)


def _adam_step(graphdef: nnx.GraphDef, loss_fn: Callable[..., jax.Array] | IterationLoss,
               optimizer: optax.GradientTransformation):
  """step(params, opt_state, rest, args) → (params, opt_state, loss): one update of the model
  nnx.merge(graphdef, params, rest) on loss_fn(model, *args) (an IterationLoss: fn(model, iteration, *args),
  iteration Adam's count of updates made); `fit` runs it, `fit_seeds` vmaps it."""
  def step(params, opt_state, rest, args):
    fn = loss_fn
    if isinstance(loss_fn, IterationLoss):
      fn, args = loss_fn.fn, (optax.tree_utils.tree_get(opt_state, "count"),) + tuple(args)
    loss, grads = jax.value_and_grad(lambda p: fn(nnx.merge(graphdef, p, rest), *args))(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss
  return step


class _Loop(NamedTuple):
  """What `_iterate` runs: update(params, opt_state, iteration) → (params, opt_state, loss(es)), `iteration`
  counting updates from 1; the models it updates, their mesh, and part(tree, s): model s's share of params or
  opt_state."""
  update: Callable
  models: Sequence[nnx.Module]
  mesh: Mesh | None
  part: Callable[[Any, int], Any]


def _iterate(loop: _Loop, state: tuple, progress: list[Progress], schedule: Schedule,
             hooks: Hooks) -> list[Progress]:
  """The loop of `fit` and `fit_seeds` from progress' iteration on, state = (params, opt_state), with the
  evaluations, logs, saves and snapshots that schedule and hooks describe for each model. Updates each
  model to its kept snapshot."""
  (params, opt_state), models, part = state, loop.models, loop.part
  on_eval, log, save = hooks
  last_save, wait = time.monotonic(), sharding.one_program_at_a_time(loop.mesh)
  for iteration in range(progress[0].iteration + 1, schedule.iterations + 1):
    params, opt_state, losses = loop.update(params, opt_state, iteration)
    if wait:
      jax.block_until_ready(losses)
    evaluate = iteration % schedule.eval_every == 0 or iteration == schedule.iterations
    if save and not evaluate and time.monotonic() - last_save >= schedule.save_seconds:
      save([p._replace(iteration=iteration, params=part(params, s), opt_state=part(opt_state, s))
            for s, p in enumerate(progress)])
      last_save = time.monotonic()
    if evaluate:
      losses = [float(x) for x in np.atleast_1d(losses)]
      for s, model in enumerate(models):
        nnx.update(model, sharding.unreplicate(part(params, s), loop.mesh))
      scores = on_eval(iteration, losses) if on_eval else [None] * len(models)
      progress = [_advance(p, iteration, part(params, s), part(opt_state, s), losses[s], scores[s],
                           schedule.snapshot) for s, p in enumerate(progress)]
      for s in range(len(models)):
        log(s, _row(iteration, losses[s], scores[s]))
      if save:
        save(progress)
        last_save = time.monotonic()
  for model, p in zip(models, progress):
    nnx.update(model, sharding.unreplicate(p.best_params, loop.mesh))
  return progress


def _ignoring_iteration(update: Callable) -> Callable:
  """update(params, opt_state) as `_Loop.update`, for updates that do not depend on which one they are."""
  return lambda params, opt_state, iteration: update(params, opt_state)


def _advance(progress: Progress, iteration: int, params, opt_state, loss: float, score: float | None,
             snapshot: str) -> Progress:
  """progress after an evaluation at `iteration`: the snapshot kept by the rule, the loss recorded."""
  improved = score is not None and (progress.best_score is None or score > progress.best_score
                                    or (snapshot == "latest" and score == progress.best_score))
  return Progress(iteration, params, opt_state,
                  params if improved or progress.best_iteration is None else progress.best_params,
                  iteration if improved else progress.best_iteration,
                  score if improved else progress.best_score, progress.losses + [[iteration, loss]])


def _row(iteration: int, loss: float, score: float | None) -> dict:
  return {"iteration": iteration, "loss": loss, **({"validation": score} if score is not None else {})}


def _stack(trees: Sequence[Any]) -> Any:
  return jax.tree.map(lambda *xs: jnp.stack(xs), *trees)


def _unstack(tree: Any, index: int) -> Any:
  return jax.tree.map(lambda x: x[index], tree)
