"""Whole-stack decoding with a hierarchy's own networks: the stack lattice's inputs built from a PHP
hierarchy give, on an annotated demonstration, exactly the log-probability that following the executor's
semantics step by step with the same networks gives."""
import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax.analysis import decoding
from php_jax.envs import datasets, tasks
from php_jax.inference import stack_lattice
from php_jax.model import PHPHierarchy
from php_jax.training import objective

NANOCRAFT = tasks.get("nanocraft")
# objective.stack_inputs as one compiled program (capacity static), not op by op.
_stack_inputs = nnx.jit(objective.stack_inputs, static_argnums=1)


def _by_hand(hierarchy: PHPHierarchy, obs, actions, procs, taus, length) -> float:
  """log P(actions, stack | observations) by walking the executor's semantics with the networks."""
  depth = len(hierarchy.levels)

  def call(level, t, proc, tau, callee):
    return hierarchy.levels[level].op_log_probs(obs[t][None], jnp.array([float(tau)]))[0][0, proc, 0, callee]

  def stop(level, t, proc, tau, stops):
    z = hierarchy.levels[level].termination_logits(obs[t + 1][None], jnp.array([float(tau)]))[0, proc, 0]
    return jax.nn.log_sigmoid(z if stops else -z)

  total = 0.0
  for t in range(length):
    if t == 0:
      fresh = 0
    else:
      resumed = max(i for i in range(depth) if taus[t, i] == taus[t - 1, i] + 1)
      fresh = resumed
    for level in range(fresh, depth - 1):  # the push chain below the resuming level (from the root at t = 0)
      total += call(level, t, procs[t, level], taus[t, level], procs[t, level + 1])
    total += hierarchy.levels[-1].log_op(obs[t][None], jnp.array([float(taus[t, -1])]),
                                         actions[t][None])[0, procs[t, -1], 0]
    # Stops from the lowest level up to the level that continues; after the last step every level stops.
    resumes = None if t == length - 1 else max(i for i in range(depth) if taus[t + 1, i] == taus[t, i] + 1)
    for level in range(depth - 1, -1 if resumes is None else resumes - 1, -1):
      total += stop(level, t, procs[t, level], taus[t, level], level != resumes)
  return float(total)


def test_stack_inputs_give_the_executor_semantics_log_probability():
  batch = datasets.training_demos(NANOCRAFT, 2, 3, 3)
  hierarchy = PHPHierarchy(NANOCRAFT.spec, hidden=(16,), rngs=nnx.Rngs(4))
  capacity = (20, 6, 4)
  for b in range(3):
    n = int(batch.length[b])
    obs, act = np.asarray(batch.observations[b]), np.asarray(batch.actions[b])
    procs, taus = np.asarray(batch.procedures[b]), np.asarray(batch.counters[b])
    inputs = _stack_inputs(hierarchy, capacity, jnp.asarray(obs), jnp.asarray(act), jnp.asarray(n))
    annotated = stack_lattice.forward_backward(inputs, jnp.asarray(procs), jnp.asarray(taus)).log_likelihood
    np.testing.assert_allclose(annotated, _by_hand(hierarchy, obs, act, procs, taus, n), rtol=1e-4)
    free = stack_lattice.forward_backward(inputs).log_likelihood
    assert annotated < free < 0  # the sum over every stack exceeds one of its paths


def test_decode_returns_the_viterbi_stacks_and_likelihoods():
  batch = datasets.training_demos(NANOCRAFT, 2, 5, 0)
  hierarchy = PHPHierarchy(NANOCRAFT.spec, hidden=(16,), rngs=nnx.Rngs(4))
  capacity = (20, 6, 4)
  decoded = decoding.decode(hierarchy, capacity, batch, chunk=2)  # chunks of 2, the last one padded
  for b in range(5):
    inputs = _stack_inputs(hierarchy, capacity, batch.observations[b], batch.actions[b], batch.length[b])
    path = stack_lattice.viterbi(inputs)
    np.testing.assert_allclose(decoded.log_likelihood[b], stack_lattice.forward_backward(inputs).log_likelihood,
                               rtol=1e-5)
    np.testing.assert_array_equal(decoded.procedures[b], path.procedures)
    np.testing.assert_array_equal(decoded.counters[b], path.counters)


def test_log_likelihood_per_step_counts_only_the_demonstrations_some_stack_fits():
  per_step, unfit = decoding.log_likelihood_per_step(np.array([-3.0, -np.inf, -1.0]), np.array([2, 5, 2]))
  assert per_step == -1.0 and unfit == 1  # (−3 − 1) / (2 + 2): the unfit demonstration's 5 steps left out
  assert decoding.log_likelihood_per_step(np.array([-np.inf]), np.array([3])) == (None, 1)


def test_log_likelihood_alone_equals_forward_backward_and_has_its_gradient():
  batch = datasets.training_demos(NANOCRAFT, 2, 2, 2)
  hierarchy = PHPHierarchy(NANOCRAFT.spec, hidden=(16,), rngs=nnx.Rngs(4))
  inputs = _stack_inputs(hierarchy, (20, 6, 4), batch.observations[1], batch.actions[1], batch.length[1])
  for annotation in ((None, None), (batch.procedures[1], None)):
    posterior = stack_lattice.forward_backward(inputs, *annotation)
    np.testing.assert_allclose(stack_lattice.log_likelihood(inputs, *annotation), posterior.log_likelihood, rtol=1e-6)
    grad = jax.grad(lambda act: stack_lattice.log_likelihood(inputs._replace(log_act=act), *annotation))(inputs.log_act)
    np.testing.assert_allclose(grad, posterior.marginals[-1], atol=1e-5)
