r"""Embedding php_jax's E-step in your own JAX model: a loss on your networks' log-probabilities.

Your model, whatever it is, produces the lattice's four log-probability tensors for each demonstration;
`php_jax.forward_backward(...).log_likelihood` is the exact log P(actions | observations) marginalised over
every segmentation into procedure calls, and `jax.grad` of it is the Expectation–Gradient gradient.

Here the "user model" is a plain-JAX softmax policy: each of K procedures has, per counter τ, a table of action
logits and a stop logit, and a root picks procedures from the observation. Data: demonstrations of a two-level
program that a weak learner must segment. Run:

  python examples/embed_estep.py --steps=300
"""
from __future__ import annotations

import argparse

import jax
import jax.numpy as jnp
import optax

import php_jax

K, C, NUM_ACTIONS, OBS_DIM = 2, 4, 3, 2


def make_demonstrations(key, num_demos=32, num_steps=24):
  """Procedure 0 emits (0, 1) then returns; procedure 1 emits (2, 2, 2) then returns; the observation's
  first coordinate says which one the root calls next. Returns observations [B, T, 2], actions [B, T], length [B]."""
  def one(key):
    choices = jax.random.bernoulli(key, 0.5, (num_steps,)).astype(jnp.int32)
    actions, obs = [], []
    for c in choices.tolist():
      body = [0, 1] if c == 0 else [2, 2, 2]
      for i, a in enumerate(body):
        actions.append(a)
        obs.append([float(c), float(i == 0)])
    return actions[:num_steps], obs[:num_steps]
  acts, obss = zip(*(one(k) for k in jax.random.split(key, num_demos)))
  return jnp.array(obss), jnp.array(acts), jnp.full((num_demos,), num_steps)


def init_params(key):
  k1, k2, k3 = jax.random.split(key, 3)
  return {"root": 0.1 * jax.random.normal(k1, (OBS_DIM, K)),
          "op": 0.1 * jax.random.normal(k2, (K, C, NUM_ACTIONS)),
          "stop": 0.1 * jax.random.normal(k3, (K, C))}


def lattice_inputs(params, observations, actions):
  """Your networks → the E-step's inputs for one demonstration: [T, K], and [T, K, C] three times."""
  num_steps = actions.shape[0]
  log_root = jax.nn.log_softmax(observations @ params["root"], axis=-1)
  log_op_all = jax.nn.log_softmax(params["op"], axis=-1)                     # [K, C, A]
  log_op = jnp.moveaxis(log_op_all[:, :, actions], -1, 0)                     # [T, K, C]
  stop_logit = jnp.broadcast_to(params["stop"], (num_steps, K, C))
  return log_root, log_op, jax.nn.log_sigmoid(stop_logit), jax.nn.log_sigmoid(-stop_logit)


def loss_fn(params, observations, actions, length):
  def one(obs, act, n):
    return php_jax.forward_backward(*lattice_inputs(params, obs, act), length=n).log_likelihood
  return -jnp.mean(jax.vmap(one)(observations, actions, length))


def main(steps: int = 300, seed: int = 0) -> tuple[float, float]:
  data = make_demonstrations(jax.random.key(seed))
  params = init_params(jax.random.key(seed + 1))
  optimizer = optax.adam(0.05)
  opt_state = optimizer.init(params)

  @jax.jit
  def update(params, opt_state):
    loss, grads = jax.value_and_grad(loss_fn)(params, *data)
    updates, opt_state = optimizer.update(grads, opt_state)
    return optax.apply_updates(params, updates), opt_state, loss

  first = last = None
  for step in range(steps):
    params, opt_state, loss = update(params, opt_state)
    first = float(loss) if first is None else first
    last = float(loss)
    if step % 100 == 0 or step == steps - 1:
      print(f"step {step:4d}  -log P(actions) per demo = {last:.3f}")
  # Decode the first demonstration with Viterbi: the segmentation into procedure calls.
  obs, act, n = (x[0] for x in data)
  path = php_jax.viterbi(*lattice_inputs(params, obs, act), length=int(n))
  print("actions:   ", act[:12].tolist())
  print("procedure: ", path.procedure[:12].tolist())
  print("counter:   ", path.counter[:12].tolist())
  return first, last


if __name__ == "__main__":
  parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
  parser.add_argument("--steps", type=int, default=300)
  parser.add_argument("--seed", type=int, default=0)
  args = parser.parse_args()
  main(args.steps, args.seed)
