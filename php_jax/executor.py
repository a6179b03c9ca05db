"""Stack-machine rollout of a whole hierarchy inside `jit` (paper §4.1.1, DESIGN.md §3 "Executor semantics").

The stack holds one frame (procedure, τ) per level: levels are layered, so at every elementary action the
stack is full depth d. Start: push (root, 0) and descend on o_0. After each action, on the new observation,
frames whose ψ says stop are popped from the top down; if the root pops the episode ends; otherwise the first
frame that does not stop increments τ and selects its next operation, and descent continues.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from php_jax.hierarchy import HierarchySpec, Policy


class Rollout(NamedTuple):
  """One episode (add a leading batch axis under vmap). S = max_steps.

  Attributes:
    final_state: the environment state after the last step.
    observations: [S+1, obs_dim] o_0 .. o_length, zero after; None when not recorded.
    actions: [S, num_factors] int32 elementary actions; None when not recorded.
    procedures: [S, d] int32 the stack's procedure per level at each action; None when not recorded.
    counters: [S, d] int32 the stack's τ per level at each action; None when not recorded.
    length: [] int32 elementary steps taken.
    terminated: [] bool the root returned within the budget with no invalid action.
    valid: [] bool no invalid action was taken.
  """
  final_state: Any
  observations: jax.Array | None
  actions: jax.Array | None
  procedures: jax.Array | None
  counters: jax.Array | None
  length: jax.Array
  terminated: jax.Array
  valid: jax.Array


def _descend(policy: Policy, depth: int, procs, taus, start, obs, key):
  """Every level ≥ start selects its operation on obs; the callee is pushed with τ = 0."""
  for level in range(depth - 1):
    callee = policy.operation(level, procs[level], taus[level], obs, jax.random.fold_in(key, level))[0]
    below = level >= start
    procs = procs.at[level + 1].set(jnp.where(below, callee, procs[level + 1]))
    taus = taus.at[level + 1].set(jnp.where(below, 0, taus[level + 1]))
  return procs, taus


def rollout(policy: Policy, spec: HierarchySpec, env, state, max_steps: int, key: jax.Array,
            record: bool = True) -> Rollout:
  """Runs the hierarchy from the root until it returns, an invalid action, or max_steps actions.

  Args:
    policy: the hierarchy's statements (an oracle or a learned PHP); a pytree.
    spec: its HierarchySpec.
    env: an environment module with observe(state) and step(state, action); states have `.failed`.
    state: the start state.
    max_steps: static step budget.
    key: PRNG key handed to the policy (used when it samples).
    record: whether to return observations, actions and stacks.
  """
  depth = spec.num_levels
  num_factors = len(spec.action_sizes)
  obs0 = env.observe(state)
  key, descend_key = jax.random.split(key)
  zeros = jnp.zeros(depth, jnp.int32)
  procs, taus = _descend(policy, depth, zeros, zeros, 0, obs0, descend_key)
  if record:
    buffers = (jnp.zeros((max_steps + 1, obs0.shape[0]), obs0.dtype).at[0].set(obs0),
               jnp.zeros((max_steps, num_factors), jnp.int32),
               jnp.zeros((max_steps, depth), jnp.int32), jnp.zeros((max_steps, depth), jnp.int32))
  else:
    buffers = None

  def body(carry):
    t, state, procs, taus, key, _, _, buffers = carry
    key, act_key, stop_key, descend_key = jax.random.split(key, 4)
    obs = env.observe(state)
    action = policy.operation(depth - 1, procs[-1], taus[-1], obs, act_key)
    state = env.step(state, action)
    new_obs = env.observe(state)
    if record:
      observations, actions, stack_procs, stack_taus = buffers
      buffers = (observations.at[t + 1].set(new_obs), actions.at[t].set(action),
                 stack_procs.at[t].set(procs), stack_taus.at[t].set(taus))
    stops = jnp.stack([policy.terminates(level, procs[level], taus[level], new_obs,
                                         jax.random.fold_in(stop_key, level)) for level in range(depth)])
    root_returned = jnp.all(stops)
    resume = depth - 1 - jnp.argmin(stops[::-1])  # the deepest frame that does not stop
    taus = taus.at[resume].add(1)
    procs, taus = _descend(policy, depth, procs, taus, resume, new_obs, descend_key)
    done = root_returned | state.failed
    return t + 1, state, procs, taus, key, done, root_returned & ~state.failed, buffers

  def cond(carry):
    t, done = carry[0], carry[5]
    return (~done) & (t < max_steps)

  init = (jnp.int32(0), state, procs, taus, key, jnp.zeros((), bool), jnp.zeros((), bool), buffers)
  t, state, _, _, _, _, terminated, buffers = jax.lax.while_loop(cond, body, init)
  recorded = buffers if record else (None,) * 4
  return Rollout(state, *recorded, length=t, terminated=terminated, valid=~state.failed)


@functools.partial(jax.jit, static_argnames=("spec", "env", "max_steps", "record"))
def rollout_batch(policy: Policy, spec: HierarchySpec, env, states, keys, max_steps: int,
                  record: bool = True) -> Rollout:
  """`rollout` vmapped over a batch of start states [B, ...] and keys [B]; compiled once per shape."""
  return jax.vmap(lambda s, k: rollout(policy, spec, env, s, max_steps, k, record))(states, keys)
