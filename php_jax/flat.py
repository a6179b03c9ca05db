"""The flat baselines a user would pick instead of PHPs: a recurrent policy (an LSTM or a GRU) trained by
behaviour cloning on the demonstrations' elementary actions (call stacks ignored), run in the same environments on
the same problems.

At each step t the recurrent cell reads o_t and the previous action, then either stops (the episode ends, as when a
PHP root returns) or emits an action, one categorical per action factor. Training maximises
Σ_t<T [log p(a_t | o_≤t) + log p(continue)] + log p(stop at T) by Adam (full-batch or on minibatches), with the
same snapshot rule as PHP training: the latest (or earliest) snapshot with the best validation accuracy. It acts
greedily, or with `sample` draws each action and the stop from its distributions.
"""
from __future__ import annotations

import functools
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import encoders, executor, fitting
from php_jax.demos import Demonstration

CELLS = ("lstm", "gru")


class FlatModel(NamedTuple):
  """A flat baseline to train: its recurrent cell (one of CELLS) and hidden units."""
  cell: str
  hidden: int

  @property
  def name(self) -> str:
    return model_name(self.cell)


def model_name(cell: str) -> str:
  """The name a flat policy with this cell goes by (`--model`, results.json, model.json): flat_lstm, flat_gru."""
  return f"flat_{cell}"


MODEL_CELLS = {model_name(cell): cell for cell in CELLS}  # a flat baseline's name → its cell


class FlatPolicy(nnx.Module):
  """A recurrent cell (`cell`: "lstm" or "gru", `hidden` units) over (o_t, one-hot a_{t−1}) with a factorized
  action head and a stop logit. With structured observation fields (`encoders.structured`) it reads o_t through
  the same encoder a PHP level would (`encoders.Encoder`, encoders.DEFAULT_WIDTH wide), so that a comparison
  separates what the hierarchy brings from what the encoder brings. Raises ValueError for another cell."""

  def __init__(self, obs_dim: int, action_sizes: tuple[int, ...], hidden: int = 128,
               fields: tuple[encoders.Field, ...] | None = None, sample: bool = False, cell: str = "lstm", *,
               rngs: nnx.Rngs):
    if cell not in CELLS:
      raise ValueError(f"cell must be one of {', '.join(CELLS)}; got {cell!r}")
    self.obs_dim = obs_dim
    self.sample = sample
    self.action_sizes = tuple(action_sizes)
    self.hidden = hidden
    self.cell_kind = cell
    self.encoder = encoders.Encoder(fields, encoders.DEFAULT_WIDTH, rngs=rngs) if encoders.structured(fields) else None
    features = obs_dim if self.encoder is None else self.encoder.width
    recurrent = nnx.LSTMCell if cell == "lstm" else nnx.GRUCell
    self.cell = recurrent(features + sum(action_sizes), hidden, rngs=rngs)
    self.head = nnx.Linear(hidden, sum(action_sizes) + 1, rngs=rngs)

  @property
  def name(self) -> str:
    return model_name(self.cell_kind)

  def initial_carry(self):
    """The cell's state before the first step: (c, h) [hidden] each for an LSTM, h [hidden] for a GRU."""
    zeros = jnp.zeros(self.hidden, jnp.float32)
    return (zeros, zeros) if self.cell_kind == "lstm" else zeros

  def step(self, carry, obs: jax.Array, prev_action: jax.Array):
    """obs [D], prev_action [F] int (−1 before the first action) → (carry, [log-probs per factor], stop logit)."""
    previous = [jax.nn.one_hot(prev_action[f], n) for f, n in enumerate(self.action_sizes)]
    obs = jnp.asarray(obs, jnp.float32)
    obs = obs if self.encoder is None else self.encoder(obs[None])[0]
    carry, h = self.cell(carry, jnp.concatenate([obs, *previous]))
    out = self.head(h)
    splits = np.cumsum(self.action_sizes)[:-1]
    factors = [jax.nn.log_softmax(part) for part in jnp.split(out[:-1], splits)]
    return carry, factors, out[-1]

  def decide(self, factors: list[jax.Array], stop_logit: jax.Array, key: jax.Array) -> tuple[jax.Array, jax.Array]:
    """`step`'s outputs → (action [F] int32, stop []): the most likely of each, or drawn from them (with key)
    where self.sample."""
    if self.sample:
      action_keys = jax.random.split(key, len(factors) + 1)
      action = jnp.stack([jax.random.categorical(k, lp) for k, lp in zip(action_keys[1:], factors)])
      return action.astype(jnp.int32), jax.random.bernoulli(action_keys[0], jax.nn.sigmoid(stop_logit))
    return jnp.stack([jnp.argmax(lp) for lp in factors]).astype(jnp.int32), stop_logit > 0

  def log_likelihood(self, observations: jax.Array, actions: jax.Array, length: jax.Array) -> jax.Array:
    """log p(actions, stop at `length` | observations). observations [T+1, D], actions [T, F], length [] → []."""
    num_steps = actions.shape[0]
    previous = jnp.concatenate([jnp.full((1, actions.shape[1]), -1, actions.dtype), actions])  # [T+1, F]
    targets = jnp.concatenate([actions, jnp.zeros((1, actions.shape[1]), actions.dtype)])

    def body(carry, inputs):
      obs, prev, target, t = inputs
      carry, factors, stop = self.step(carry, obs, prev)
      log_action = sum(lp[target[f]] for f, lp in enumerate(factors))
      term = jnp.where(t < length, log_action + jax.nn.log_sigmoid(-stop), jax.nn.log_sigmoid(stop))
      return carry, jnp.where(t <= length, term, 0.0)

    _, terms = jax.lax.scan(body, self.initial_carry(),
                            (observations, previous, targets, jnp.arange(num_steps + 1)))
    return jnp.sum(terms)


def _act(policy: FlatPolicy, env, machine, key):
  """One decision of one episode: stop, or act. machine = (state, carry, previous action)."""
  state, carry, previous = machine
  carry, factors, stop_logit = policy.step(carry, env.observe(state), previous)
  action, stop = policy.decide(factors, stop_logit, key)
  return (env.step(state, action), carry, action), stop


@functools.partial(jax.jit, static_argnames=("env", "max_steps"))
def rollout_batch(policy: FlatPolicy, env, states, keys, max_steps: int) -> executor.Rollout:
  """Episodes from a batch of start states [B, ...] until each stops, fails or spends max_steps actions,
  greedy or (policy.sample) drawn with keys [B] (step t's key folds t into the episode's); the same outcome
  fields as the hierarchy executor's (nothing recorded)."""
  batch = jax.tree.leaves(states)[0].shape[0]
  carry = jax.tree.map(lambda x: jnp.broadcast_to(x, (batch,) + x.shape), policy.initial_carry())
  previous = jnp.full((batch, len(policy.action_sizes)), -1, jnp.int32)
  act = jax.vmap(lambda m, k: _act(policy, env, m, k))

  def body(loop):
    t, machines, done, stopped, length, failed_action = loop
    advanced, stop = act(machines, jax.vmap(lambda k: jax.random.fold_in(k, t))(keys))
    moving = ~done & ~stop & (t < max_steps)  # the last pass only decides whether to stop

    def keep(new, old):
      return jnp.where(moving.reshape((batch,) + (1,) * (new.ndim - 1)), new, old)

    machines = jax.tree.map(keep, advanced, machines)
    stopped = stopped | (~done & stop)
    failed_action = jnp.where((moving & machines[0].failed)[:, None], machines[2], failed_action)
    done = done | stop | machines[0].failed
    return t + 1, machines, done, stopped, length + moving, failed_action

  def cond(loop):
    return (loop[0] <= max_steps) & ~jnp.all(loop[2])

  init = (jnp.int32(0), (states, carry, previous), jnp.zeros(batch, bool), jnp.zeros(batch, bool),
          jnp.zeros(batch, jnp.int32), jnp.zeros((batch, len(policy.action_sizes)), jnp.int32))
  _, (final, _, _), _, stopped, length, failed_action = jax.lax.while_loop(cond, body, init)
  valid = ~final.failed
  return executor.Rollout(final, None, None, None, None, length=length, terminated=stopped & valid,
                          valid=valid, failed_action=failed_action)


def train(policy: FlatPolicy, demos: Demonstration, schedule: fitting.Schedule,
          hooks: fitting.Hooks = fitting.Hooks()) -> dict:
  """Behaviour cloning: Adam on −mean log p(demonstration) over every demonstration, or with
  schedule.batch_size a minibatch (`fitting.fit`: the snapshot with the best hooks.on_eval score is kept,
  else the final one). Updates `policy` in place. Returns a report."""
  data = [(np.asarray(demos.observations), np.asarray(demos.actions), np.asarray(demos.length))]

  def loss(model, buckets):
    [(observations, actions, length)] = buckets
    return -jnp.mean(jax.vmap(model.log_likelihood)(observations, actions, length))
  progress = fitting.fit(policy, loss, schedule, hooks, args=(data,))
  return {"losses": progress.losses, "best_iteration": progress.best_iteration, "validation": progress.best_score}
