"""Full-batch Adam with the project's snapshot rule and resumable progress: the loop that both the PHP
levels (php_jax.train) and the flat LSTM baseline (php_jax.flat_lstm) train with."""
from __future__ import annotations

import functools
import time
from typing import Any, Callable, NamedTuple

import jax
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

  def step(params, opt_state, args):
    loss, grads = jax.value_and_grad(lambda p: loss_fn(nnx.merge(graphdef, p, rest), *args))(params)
    updates, opt_state = optimizer.update(grads, opt_state, params)
    return optax.apply_updates(params, updates), opt_state, loss

  if mesh is None:  # the data as constants, folded into the program by XLA: one device's numbers as before meshes
    update = jax.jit(lambda params, opt_state: step(params, opt_state, args))
  else:  # as arguments: a constant would sit whole on one device
    update = functools.partial(jax.jit(step), args=args)
  params, opt_state = sharding.replicate((progress.params, progress.opt_state), mesh)
  last_save = time.monotonic()
  for iteration in range(progress.iteration + 1, iterations + 1):
    params, opt_state, loss = update(params, opt_state)
    evaluate = iteration % eval_every == 0 or iteration == iterations
    if save and not evaluate and time.monotonic() - last_save >= save_seconds:
      save(progress._replace(iteration=iteration, params=params, opt_state=opt_state))
      last_save = time.monotonic()
    if evaluate:
      loss = float(loss)
      nnx.update(model, sharding.unreplicate(params, mesh))
      score = on_eval(iteration, loss) if on_eval else None
      improved = score is not None and (progress.best_score is None or score > progress.best_score
                                        or (snapshot == "latest" and score == progress.best_score))
      progress = Progress(
          iteration, params, opt_state,
          params if improved or progress.best_iteration is None else progress.best_params,
          iteration if improved else progress.best_iteration,
          score if improved else progress.best_score, progress.losses + [[iteration, loss]])
      log({"iteration": iteration, "loss": loss, **({"validation": score} if score is not None else {})})
      if save:
        save(progress)
        last_save = time.monotonic()
  nnx.update(model, sharding.unreplicate(progress.best_params, mesh))
  return progress
