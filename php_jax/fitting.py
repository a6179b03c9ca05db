"""Full-batch Adam with the project's snapshot rule and resumable progress: the loop that the PHP levels
(php_jax.train), joint training (php_jax.joint) and the flat LSTM baseline (php_jax.flat_lstm) train with
(`fit`), and the same loop and update step for several seeds' models at once, vmapped (`fit_seeds`, for
php_jax.train.train_seeds)."""
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


def fit(model: nnx.Module, loss_fn: Callable[..., jax.Array], iterations: int, learning_rate: float,
        eval_every: int, on_eval: Callable[[int, float], float | None] | None = None,
        log: Callable[[dict], None] = print, resume: Progress | None = None,
        save: Callable[[Progress], None] | None = None, snapshot: str = "latest",
        save_seconds: float = 30.0, args: tuple = (), mesh: Mesh | None = None) -> Progress:
  """Full-batch Adam on loss_fn(model, *args) []. Updates `model` in place to the kept snapshot.

  args (the data) follow the model into loss_fn: as constants of the compiled update without a mesh, as its
  arguments with one (arrays split over `mesh`); then the parameters and optimizer state are replicated on
  the mesh, and the model gets them back as arrays of the default device.

  Every eval_every iterations and at the end: on_eval(iteration, loss) may return a validation score (the
  snapshot with the highest score is kept, the latest or the earliest among equals as `snapshot` says;
  without scores, the final iterate), then the row is logged and save(progress) called; save is also called
  when save_seconds have passed since the last save. resume continues from a saved Progress, to the same
  result as an uninterrupted fit.
  """
  if snapshot not in SNAPSHOT_RULES:
    raise ValueError(f"snapshot must be one of {SNAPSHOT_RULES}; got {snapshot!r}")
  graphdef, params, rest = nnx.split(model, nnx.Param, ...)
  optimizer = optax.adam(learning_rate)
  progress = resume if resume is not None else Progress(0, params, optimizer.init(params), params, None, None,
                                                        [])

  step = _adam_step(graphdef, loss_fn, optimizer)
  if mesh is None:  # the data as constants, folded into the program by XLA
    update = jax.jit(lambda params, opt_state: step(params, opt_state, rest, args))
  else:  # as arguments: a constant would sit whole on one device
    update = functools.partial(jax.jit(lambda params, opt_state, args: step(params, opt_state, rest, args)),
                               args=args)
  params, opt_state = sharding.replicate((progress.params, progress.opt_state), mesh)
  [progress] = _iterate(update, params, opt_state, [progress], [model], iterations, eval_every,
                        (lambda iteration, losses: [on_eval(iteration, losses[0])]) if on_eval else None,
                        lambda s, row: log(row), (lambda progresses: save(progresses[0])) if save else None,
                        snapshot, save_seconds, mesh, part=lambda tree, s: tree)
  return progress


def fit_seeds(models: Sequence[nnx.Module], loss_fn: Callable[..., jax.Array], iterations: int,
              learning_rate: float, eval_every: int,
              on_eval: Callable[[int, list[float]], list[float | None]] | None = None,
              log: Callable[[int, dict], None] = lambda s, row: print(s, row),
              resume: list[Progress] | None = None, save: Callable[[list[Progress]], None] | None = None,
              snapshot: str = "latest", save_seconds: float = 30.0, args: tuple = (),
              mesh: Mesh | None = None) -> list[Progress]:
  """`fit` for S independent models of one architecture (one per seed), as one vmapped program: model s is
  trained on loss_fn(models[s], *args_s) [], where args' leaves are stacked along a leading S axis, and keeps
  its own snapshot. on_eval(iteration, losses) returns each model's score (or None), log(s, row) gets model
  s's rows, save and resume take one Progress per model (each as `fit` makes it). With a mesh (args placed on
  it by the caller), the parameters and optimizer states are replicated on it. Updates each model in place to
  its kept snapshot; returns the Progress of each."""
  if snapshot not in SNAPSHOT_RULES:
    raise ValueError(f"snapshot must be one of {SNAPSHOT_RULES}; got {snapshot!r}")
  splits = [nnx.split(model, nnx.Param, ...) for model in models]
  graphdef, rest = splits[0][0], _stack([r for _, _, r in splits])
  optimizer = optax.adam(learning_rate)
  progress = resume if resume is not None else [Progress(0, p, optimizer.init(p), p, None, None, [])
                                                for _, p, _ in splits]

  update = jax.jit(jax.vmap(_adam_step(graphdef, loss_fn, optimizer)))
  params, opt_state = sharding.replicate((_stack([p.params for p in progress]),
                                          _stack([p.opt_state for p in progress])), mesh)
  rest = sharding.replicate(rest, mesh)
  return _iterate(lambda params, opt_state: update(params, opt_state, rest, args), params, opt_state, progress,
                  models, iterations, eval_every, on_eval, log, save, snapshot, save_seconds, mesh, part=_unstack)


def _adam_step(graphdef: nnx.GraphDef, loss_fn: Callable[..., jax.Array], optimizer: optax.GradientTransformation):
  """step(params, opt_state, rest, args) → (params, opt_state, loss): one update of the model
  nnx.merge(graphdef, params, rest) on loss_fn(model, *args); `fit` runs it, `fit_seeds` vmaps it."""
  def step(params, opt_state, rest, args):
    loss, grads = jax.value_and_grad(lambda p: loss_fn(nnx.merge(graphdef, p, rest), *args))(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss
  return step


def _iterate(update, params, opt_state, progress: list[Progress], models: Sequence[nnx.Module], iterations: int,
             eval_every: int, on_eval, log, save, snapshot: str, save_seconds: float, mesh: Mesh | None,
             part: Callable[[Any, int], Any]) -> list[Progress]:
  """The loop of `fit` and `fit_seeds`: update(params, opt_state) → (params, opt_state, loss(es)) from
  progress' iteration on, with the evaluations, logs, saves and snapshots they describe for each model;
  part(tree, s) is model s's share of params or opt_state. Updates each model to its kept snapshot."""
  last_save = time.monotonic()
  for iteration in range(progress[0].iteration + 1, iterations + 1):
    params, opt_state, losses = update(params, opt_state)
    evaluate = iteration % eval_every == 0 or iteration == iterations
    if save and not evaluate and time.monotonic() - last_save >= save_seconds:
      save([p._replace(iteration=iteration, params=part(params, s), opt_state=part(opt_state, s))
            for s, p in enumerate(progress)])
      last_save = time.monotonic()
    if evaluate:
      losses = [float(x) for x in np.atleast_1d(losses)]
      for s, model in enumerate(models):
        nnx.update(model, sharding.unreplicate(part(params, s), mesh))
      scores = on_eval(iteration, losses) if on_eval else [None] * len(models)
      progress = [_advance(p, iteration, part(params, s), part(opt_state, s), losses[s], scores[s], snapshot)
                  for s, p in enumerate(progress)]
      for s in range(len(models)):
        log(s, _row(iteration, losses[s], scores[s]))
      if save:
        save(progress)
        last_save = time.monotonic()
  for model, p in zip(models, progress):
    nnx.update(model, sharding.unreplicate(p.best_params, mesh))
  return progress


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
