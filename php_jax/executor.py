"""Stack-machine rollout of a whole hierarchy inside `jit` (paper §4.1.1).

The stack holds one frame (procedure, τ) per level: levels are layered, so at every elementary action the
stack is full depth d. Start: push (root, 0) and descend on o_0. After each action, on the new observation,
frames whose ψ says stop are popped from the top down; if the root pops the episode ends; otherwise the first
frame that does not stop increments τ and selects its next operation, and descent continues.

A policy that remembers what it observed (a learned hierarchy with a memory: `initial_memory`, `remember`,
`recall`) has its memory carried beside the stack: updated on each new observation with the action that led
to it, and every decision asked of the policy bound to it.
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple

import jax
import jax.numpy as jnp

from php_jax.hierarchy import HierarchySpec, Policy, check_size
from php_jax.inference.lattice_inputs import check_key


class Rollout(NamedTuple):
  """A batch of episodes; every field has a leading batch axis B. S = max_steps.

  Attributes:
    final_state: the environment state after the last step.
    observations: [B, S+1, obs_dim] o_0 .. o_length, zero after; None when not recorded.
    actions: [B, S, num_factors] int32 elementary actions (zero after length); None when not recorded.
    procedures: [B, S, d] int32 the stack's procedure per level at each action; None when not recorded.
    counters: [B, S, d] int32 the stack's τ per level at each action; None when not recorded.
    length: [B] int32 elementary steps taken.
    terminated: [B] bool the root returned within the budget with no invalid action.
    valid: [B] bool no invalid action was taken.
    failed_action: [B, num_factors] int32 the invalid action, always the episode's last (zero where valid).
  """
  final_state: Any
  observations: jax.Array | None
  actions: jax.Array | None
  procedures: jax.Array | None
  counters: jax.Array | None
  length: jax.Array
  terminated: jax.Array
  valid: jax.Array
  failed_action: jax.Array


def _descend(policy: Policy, depth: int, procs, taus, start, obs, key):
  """Every level ≥ start selects its operation on obs; the callee is pushed with τ = 0."""
  for level in range(depth - 1):
    callee = policy.operation(level, procs[level], taus[level], obs, jax.random.fold_in(key, level))[0]
    below = level >= start
    procs = procs.at[level + 1].set(jnp.where(below, callee, procs[level + 1]))
    taus = taus.at[level + 1].set(jnp.where(below, 0, taus[level + 1]))
  return procs, taus


class _Machine(NamedTuple):
  """One problem's machine between steps: environment state, stack [d] procedures and counters, PRNG key, and
  the policy's memory (() for a policy without one)."""
  state: Any
  procs: jax.Array
  taus: jax.Array
  key: jax.Array
  memory: Any


def initial_memory(policy) -> Any:
  """A policy's memory before an episode (`PHPHierarchy.initial_memory`); () for one that keeps none."""
  return policy.initial_memory() if hasattr(policy, "remember") else ()


def remembered(policy, memory, obs: jax.Array, previous: jax.Array) -> Any:
  """The policy's memory after observing obs [D], reached by the action previous [F] (−1 at the start)."""
  return policy.remember(memory, obs, previous) if hasattr(policy, "remember") else memory


def recalled(policy, memory) -> Policy:
  """The policy whose decisions read this memory (the policy itself where it keeps none)."""
  return policy.recall(memory) if hasattr(policy, "recall") else policy


def start_stack(policy: Policy, spec: HierarchySpec, obs: jax.Array, key: jax.Array):
  """The stack [d] procedures and counters that pushes (root, 0) and descends on o_0 (obs [D])."""
  zeros = jnp.zeros(spec.num_levels, jnp.int32)
  return _descend(policy, spec.num_levels, zeros, zeros, 0, obs, key)


def elementary_action(policy: Policy, spec: HierarchySpec, procs, taus, obs, key) -> jax.Array:
  """The action [F] int32 that the stack's last frame takes on obs."""
  return policy.operation(spec.num_levels - 1, procs[-1], taus[-1], obs, key)


def next_stack(policy: Policy, spec: HierarchySpec, procs, taus, obs, key):
  """After an action, on the new observation obs: pops the frames that stop, resumes and descends.

  Returns (procedures [d], counters [d], root returned []); the stack is meaningless when the root returned.
  """
  depth = spec.num_levels
  stop_key, descend_key = jax.random.split(key)
  stops = jnp.stack([policy.terminates(level, procs[level], taus[level], obs,
                                       jax.random.fold_in(stop_key, level)) for level in range(depth)])
  resume = depth - 1 - jnp.argmin(stops[::-1])  # the deepest frame that does not stop
  new_procs, new_taus = _descend(policy, depth, procs, taus.at[resume].add(1), resume, obs, descend_key)
  return new_procs, new_taus, jnp.all(stops)


def _start(policy: Policy, spec: HierarchySpec, env, state, key) -> _Machine:
  """Pushes (root, 0) and descends on o_0."""
  key, descend_key = jax.random.split(key)
  obs = env.observe(state)
  memory = remembered(policy, initial_memory(policy), obs, jnp.full(len(spec.action_sizes), -1, jnp.int32))
  procs, taus = start_stack(recalled(policy, memory), spec, obs, descend_key)
  return _Machine(state, procs, taus, key, memory)


def _advance(policy: Policy, spec: HierarchySpec, env, machine: _Machine):
  """One elementary step: act, observe, pop the frames that stop, resume and descend.

  Returns (machine, (new observation, action, stack procedures, stack counters), root returned).
  """
  state, procs, taus, key, memory = machine
  key, act_key, stack_key = jax.random.split(key, 3)
  action = elementary_action(recalled(policy, memory), spec, procs, taus, env.observe(state), act_key)
  state = env.step(state, action)
  obs = env.observe(state)
  memory = remembered(policy, memory, obs, action)
  new_procs, new_taus, returned = next_stack(recalled(policy, memory), spec, procs, taus, obs, stack_key)
  return _Machine(state, new_procs, new_taus, key, memory), (obs, action, procs, taus), returned


def rollout_batch(policy: Policy, spec: HierarchySpec, env, states, keys, max_steps: int,
                  record: bool = True) -> Rollout:
  """Runs the hierarchy from the root on a batch of start states [B, ...] until each root returns, takes an
  invalid action, or max_steps actions pass. Compiled once per shape.

  One while loop steps the whole batch (the step itself is vmapped); finished problems are frozen. Recording
  buffers are written once per step, never copied, so recording costs O(steps).

  Args:
    policy: the hierarchy's statements (an oracle or a learned PHP); a pytree.
    spec: its HierarchySpec.
    env: an environment module with observe(state) and step(state, action); states have `.failed`.
    states: batched start states.
    keys: [B] PRNG keys handed to the policy (used when it samples).
    max_steps: static step budget, an int ≥ 1.
    record: whether to return observations, actions and stacks.
  Raises:
    ValueError naming the argument: spec not a HierarchySpec, max_steps not an int ≥ 1, keys not a batch
    [B] of PRNG keys (legacy uint32 keys: [B, 2]), or states whose leading axis is not B (static checks: the
    same under jit).
  """
  if not isinstance(spec, HierarchySpec):
    raise ValueError(f"spec must be a HierarchySpec; got {spec!r}")
  max_steps = check_size("max_steps", max_steps)
  check_key(keys, "keys", batched=True)
  batch = jnp.shape(keys)[0]
  for path, leaf in jax.tree_util.tree_leaves_with_path(states):
    if jnp.ndim(leaf) == 0 or jnp.shape(leaf)[0] != batch:
      raise ValueError(f"states{jax.tree_util.keystr(path)} must have a leading batch axis of B = {batch}, the "
                       f"number of keys; got shape {jnp.shape(leaf)}")
  return _rollout_batch(policy, spec, env, states, keys, max_steps, record)


@functools.partial(jax.jit, static_argnames=("spec", "env", "max_steps", "record"))
def _rollout_batch(policy: Policy, spec: HierarchySpec, env, states, keys, max_steps: int, record: bool) -> Rollout:
  batch = keys.shape[0]
  depth, num_factors = spec.num_levels, len(spec.action_sizes)
  machines = jax.vmap(lambda s, k: _start(policy, spec, env, s, k))(states, keys)
  advance = jax.vmap(lambda m: _advance(policy, spec, env, m))
  if record:
    obs0 = jax.vmap(env.observe)(states)
    buffers = (jnp.zeros((batch, max_steps + 1, obs0.shape[-1]), obs0.dtype).at[:, 0].set(obs0),
               jnp.zeros((batch, max_steps, num_factors), jnp.int32),
               jnp.zeros((batch, max_steps, depth), jnp.int32), jnp.zeros((batch, max_steps, depth), jnp.int32))
  else:
    buffers = None
  done = jnp.zeros(batch, bool)

  def body(loop):
    t, machines, done, returned, length, failed_action, buffers = loop
    advanced, (obs, action, procs, taus), root_returned = advance(machines)
    active = ~done

    def keep_active(new, old):
      return jnp.where(active.reshape((batch,) + (1,) * (new.ndim - 1)), new, old)

    machines = jax.tree.map(keep_active, advanced, machines)
    if record:
      observations, actions, stack_procs, stack_taus = buffers
      buffers = (observations.at[:, t + 1].set(obs), actions.at[:, t].set(action),
                 stack_procs.at[:, t].set(procs), stack_taus.at[:, t].set(taus))
    returned = returned | (active & root_returned)
    failed_action = jnp.where((active & machines.state.failed)[:, None], action, failed_action)
    done = done | root_returned | machines.state.failed
    return t + 1, machines, done, returned, length + active, failed_action, buffers

  def cond(loop):
    return (loop[0] < max_steps) & ~jnp.all(loop[2])

  init = (jnp.int32(0), machines, done, jnp.zeros(batch, bool), jnp.zeros(batch, jnp.int32),
          jnp.zeros((batch, num_factors), jnp.int32), buffers)
  _, machines, _, returned, length, failed_action, buffers = jax.lax.while_loop(cond, body, init)
  valid = ~machines.state.failed
  if record:  # rows written after an episode ended are not part of it
    steps = jnp.arange(max_steps)[None, :] < length[:, None]
    observations, actions, stack_procs, stack_taus = buffers
    obs_used = jnp.arange(max_steps + 1)[None, :] <= length[:, None]
    buffers = (jnp.where(obs_used[..., None], observations, 0), jnp.where(steps[..., None], actions, 0),
               jnp.where(steps[..., None], stack_procs, 0), jnp.where(steps[..., None], stack_taus, 0))
  recorded = buffers if record else (None,) * 4
  return Rollout(machines.state, *recorded, length=length, terminated=returned & valid, valid=valid,
                 failed_action=failed_action)
