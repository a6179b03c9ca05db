"""E-step against brute-force enumeration, the EG identities, decoding, sampling and long-trace numerics."""
import jax
import jax.numpy as jnp
import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from jax.test_util import check_grads

import php_jax
from tests.inference import lattice_brute_force as bf

# (T, K, C, length): padding, C smaller than T, C larger than T, single step.
CASES = [(5, 2, 3, 5), (7, 3, 2, 5), (6, 2, 7, 6), (4, 3, 4, 2), (3, 1, 3, 3), (1, 2, 2, 1), (7, 2, 4, 7)]


def _jnp(inputs, dtype):
  return tuple(jnp.asarray(x, dtype) for x in inputs)


@pytest.mark.parametrize("shape", CASES)
@pytest.mark.parametrize("mask_prob", [0.0, 0.2])
def test_forward_backward_matches_enumeration_float64(shape, mask_prob):
  num_steps, num_procs, capacity, length = shape
  rng = np.random.default_rng(sum(shape))
  inputs = bf.random_lattice(rng, num_steps, num_procs, capacity, mask_prob=mask_prob)
  log_z, v, w, _, _ = bf.enumerate_posterior(inputs, length)
  with jax.enable_x64(True):
    post = php_jax.forward_backward(*_jnp(inputs, jnp.float64), length=length)
    np.testing.assert_allclose(post.log_likelihood, log_z, atol=1e-6)
    np.testing.assert_allclose(post.v, v, atol=1e-6)
    np.testing.assert_allclose(post.w, w, atol=1e-6)


@pytest.mark.parametrize("shape", CASES)
def test_forward_backward_matches_enumeration_float32(shape):
  num_steps, num_procs, capacity, length = shape
  inputs = bf.random_lattice(np.random.default_rng(7), num_steps, num_procs, capacity)
  log_z, v, w, _, _ = bf.enumerate_posterior(inputs, length)
  post = php_jax.forward_backward(*_jnp(inputs, jnp.float32), length=length)
  assert post.v.dtype == jnp.float32
  np.testing.assert_allclose(post.log_likelihood, log_z, atol=1e-4, rtol=1e-5)
  np.testing.assert_allclose(post.v, v, atol=1e-4)
  np.testing.assert_allclose(post.w, w, atol=1e-4)


@settings(max_examples=25, deadline=None)
@given(num_steps=st.integers(1, 6), num_procs=st.integers(1, 3), capacity=st.integers(1, 5),
       data=st.data())
def test_property_random_shapes_and_scales(num_steps, num_procs, capacity, data):
  length = data.draw(st.integers(1, num_steps))
  scale = data.draw(st.sampled_from([0.1, 1.0, 8.0]))
  seed = data.draw(st.integers(0, 2**16))
  inputs = bf.random_lattice(np.random.default_rng(seed), num_steps, num_procs, capacity, scale=scale)
  log_z, v, w, _, _ = bf.enumerate_posterior(inputs, length)
  with jax.enable_x64(True):
    post = php_jax.forward_backward(*_jnp(inputs, jnp.float64), length=length)
    np.testing.assert_allclose(post.log_likelihood, log_z, atol=1e-6, rtol=1e-9)
    np.testing.assert_allclose(post.v, v, atol=1e-6)
    np.testing.assert_allclose(post.w, w, atol=1e-6)


@pytest.mark.parametrize("shape", CASES)
def test_viterbi_matches_brute_force_argmax(shape):
  num_steps, num_procs, capacity, length = shape
  inputs = bf.random_lattice(np.random.default_rng(3), num_steps, num_procs, capacity, scale=3.0)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, length)
  best = paths[int(np.argmax(log_probs))]
  with jax.enable_x64(True):
    path = php_jax.viterbi(*_jnp(inputs, jnp.float64), length=length)
  assert [(int(h), int(t)) for h, t in zip(path.procedures[:length], path.counters[:length])] == best
  assert np.all(np.asarray(path.procedures[length:]) == php_jax.NO_FRAME)
  np.testing.assert_allclose(path.log_prob, log_probs.max(), atol=1e-8)


def test_posterior_samples_match_enumerated_posterior():
  num_steps, num_procs, capacity, length = 5, 2, 3, 4
  inputs = bf.random_lattice(np.random.default_rng(11), num_steps, num_procs, capacity)
  log_z, _, _, paths, log_probs = bf.enumerate_posterior(inputs, length)
  probs = np.exp(log_probs - log_z)
  num_samples = 20_000
  keys = jax.random.split(jax.random.key(0), num_samples)
  samples = jax.jit(jax.vmap(php_jax.sample_posterior, in_axes=(0, None, None, None, None, None)))(
      keys, *_jnp(inputs, jnp.float32), length)
  index = {tuple(p): i for i, p in enumerate(paths)}
  counts = np.zeros(len(paths))
  procs, taus = np.asarray(samples.procedures), np.asarray(samples.counters)
  for proc, tau in zip(procs, taus):
    counts[index[tuple(zip(proc[:length].tolist(), tau[:length].tolist()))]] += 1
  assert np.all(procs[:, length:] == php_jax.NO_FRAME)
  # Each path's frequency within 5 binomial standard deviations (+ a float32 allowance): with about 50
  # paths a false failure has probability below 1e-4 for this fixed seed's distribution.
  sigma = np.sqrt(probs * (1 - probs) / num_samples)
  assert np.all(np.abs(counts / num_samples - probs) <= 5 * sigma + 1e-4)
  # The reported log_prob is the sampled path's complete-data log-likelihood.
  first = list(zip(procs[0, :length].tolist(), taus[0, :length].tolist()))
  np.testing.assert_allclose(samples.log_prob[0], bf.path_log_prob(inputs, first), atol=1e-4)


@pytest.mark.parametrize("shape", CASES)
def test_eg_identities_gradients_are_marginals(shape):
  num_steps, num_procs, capacity, length = shape
  inputs = _jnp(bf.random_lattice(np.random.default_rng(5), num_steps, num_procs, capacity,
                                  mask_prob=0.1), jnp.float32)
  post = php_jax.forward_backward(*inputs, length=length)
  grads = jax.grad(lambda *a: php_jax.forward_backward(*a, length=length).log_likelihood,
                   argnums=(0, 1, 2, 3))(*inputs)
  g_root, g_op, g_stop, g_cont = grads
  np.testing.assert_allclose(g_op, post.v, atol=1e-6)
  np.testing.assert_allclose(g_cont, post.w, atol=1e-6)
  np.testing.assert_allclose(g_stop, post.v - post.w, atol=1e-6)
  np.testing.assert_allclose(g_root, post.v[:, :, 0], atol=1e-6)


def test_gradients_match_finite_differences_including_through_marginals():
  inputs = bf.random_lattice(np.random.default_rng(9), 5, 2, 3)
  with jax.enable_x64(True):
    args = _jnp(inputs, jnp.float64)
    weights = jnp.asarray(np.random.default_rng(1).normal(size=(5, 2, 3)))

    def loss(*a):  # exercises the log-likelihood rule and the autodiff fallback for v and w
      post = php_jax.forward_backward(*a, length=4)
      return post.log_likelihood + jnp.sum(weights * post.v) + jnp.sum(weights ** 2 * post.w)

    check_grads(loss, args, order=1, modes=["rev"], atol=1e-5, rtol=1e-5)


def test_full_annotation_gives_complete_data_log_likelihood():
  num_steps, num_procs, capacity, length = 7, 3, 4, 6
  inputs = bf.random_lattice(np.random.default_rng(2), num_steps, num_procs, capacity)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, length)
  rng = np.random.default_rng(0)
  for i in rng.choice(len(paths), size=5, replace=False):
    path = paths[i]
    proc = jnp.array([h for h, _ in path] + [-1] * (num_steps - length))
    tau = jnp.array([t for _, t in path] + [-1] * (num_steps - length))
    log_root, log_op, log_stop, log_cont = _jnp(inputs, jnp.float32)
    masked = php_jax.annotate(log_op, proc, tau)
    post = php_jax.forward_backward(log_root, masked, log_stop, log_cont, length=length)
    direct = php_jax.complete_log_likelihood(log_root, log_op, log_stop, log_cont, proc, tau, length)
    np.testing.assert_allclose(post.log_likelihood, log_probs[i], atol=1e-4)
    np.testing.assert_allclose(direct, log_probs[i], atol=1e-4)
    np.testing.assert_allclose(post.v[jnp.arange(length), proc[:length], tau[:length]], 1.0, atol=1e-6)


def test_partial_annotation_sums_over_consistent_paths():
  num_steps, num_procs, capacity, length = 6, 2, 3, 6
  inputs = bf.random_lattice(np.random.default_rng(4), num_steps, num_procs, capacity)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, length)
  proc = np.array([1, -1, -1, 0, -1, -1])   # h_0 = 1, h_3 = 0
  tau = np.array([-1, -1, 2, -1, -1, -1])   # τ_2 = 2
  keep = [all((proc[t] < 0 or h == proc[t]) and (tau[t] < 0 or c == tau[t]) for t, (h, c) in enumerate(p))
          for p in paths]
  expected = np.logaddexp.reduce(log_probs[np.array(keep)])
  log_root, log_op, log_stop, log_cont = _jnp(inputs, jnp.float32)
  post = php_jax.forward_backward(log_root, php_jax.annotate(log_op, jnp.array(proc), jnp.array(tau)),
                                  log_stop, log_cont)
  np.testing.assert_allclose(post.log_likelihood, expected, atol=1e-4)


def test_broken_annotation_has_zero_probability():
  inputs = _jnp(bf.random_lattice(np.random.default_rng(4), 4, 2, 3), jnp.float32)
  jump = (jnp.array([0, 0, 0, 1]), jnp.array([0, 2, 0, 0]))  # counter jumps 0 → 2 (values in range)
  assert php_jax.complete_log_likelihood(*inputs, *jump) == -jnp.inf
  post = php_jax.forward_backward(inputs[0], php_jax.annotate(inputs[1], *jump), *inputs[2:])
  assert post.log_likelihood == -jnp.inf
  assert np.all(np.isfinite(post.v)) and np.all(post.v == 0)
  grads = jax.grad(lambda op: php_jax.forward_backward(
      inputs[0], php_jax.annotate(op, *jump), *inputs[2:]).log_likelihood)(inputs[1])
  assert np.all(np.isfinite(grads))


def test_max_marginal_path_is_per_step_argmax_of_v():
  inputs = bf.random_lattice(np.random.default_rng(8), 6, 3, 3)
  _, v, _, _, _ = bf.enumerate_posterior(inputs, 5)
  post = php_jax.forward_backward(*_jnp(inputs, jnp.float32), length=5)
  path = php_jax.max_marginal_path(post, length=5)
  flat = v[:5].reshape(5, -1).argmax(axis=1)
  np.testing.assert_array_equal(path.procedures[:5], flat // 3)
  np.testing.assert_array_equal(path.counters[:5], flat % 3)
  assert path.procedures[5] == php_jax.NO_FRAME


@pytest.mark.parametrize("shape", [(5, 2, 3, 5), (6, 3, 2, 4), (4, 1, 4, 4)])
def test_posterior_entropy_matches_enumeration(shape):
  num_steps, num_procs, capacity, length = shape
  inputs = bf.random_lattice(np.random.default_rng(6), num_steps, num_procs, capacity, mask_prob=0.15)
  log_z, _, _, _, log_probs = bf.enumerate_posterior(inputs, length)
  with jax.enable_x64(True):
    h = php_jax.posterior_entropy(*_jnp(inputs, jnp.float64), length=length)
  np.testing.assert_allclose(h, bf.entropy(log_probs, log_z), atol=1e-6)


def test_top_level_mode_is_one_call_of_one_procedure():
  num_steps, capacity = 5, 6
  inputs = bf.random_lattice(np.random.default_rng(1), num_steps, 1, capacity)
  log_root, log_op, log_stop, log_cont = inputs
  expected = (log_root[0, 0] + sum(log_op[t, 0, t] for t in range(num_steps))
              + sum(log_cont[t, 0, t] for t in range(num_steps - 1)) + log_stop[num_steps - 1, 0, num_steps - 1])
  log_root, log_op, log_stop, log_cont = _jnp(inputs, jnp.float32)
  post = php_jax.forward_backward(log_root, log_op, php_jax.top_level(log_stop), log_cont)
  np.testing.assert_allclose(post.log_likelihood, expected, atol=1e-4)
  np.testing.assert_allclose(post.v[jnp.arange(num_steps), 0, jnp.arange(num_steps)], 1.0, atol=1e-6)


def test_vmap_over_demonstrations_with_different_lengths():
  num_steps, num_procs, capacity = 6, 2, 3
  batch = [bf.random_lattice(np.random.default_rng(s), num_steps, num_procs, capacity) for s in range(4)]
  lengths = jnp.array([6, 1, 3, 5])
  stacked = tuple(jnp.asarray(np.stack([b[i] for b in batch]), jnp.float32) for i in range(4))
  out = jax.jit(jax.vmap(php_jax.forward_backward))(*stacked, lengths)
  for i, b in enumerate(batch):
    single = php_jax.forward_backward(*_jnp(b, jnp.float32), length=int(lengths[i]))
    np.testing.assert_allclose(out.log_likelihood[i], single.log_likelihood, rtol=1e-6)
    np.testing.assert_allclose(out.v[i], single.v, atol=1e-6)


def test_long_trace_with_sharp_logits_and_masks_is_finite():
  """T = 10,000, logits ×50 and −inf masks: finite log-likelihood, marginals and gradients."""
  num_steps, num_procs, capacity = 10_000, 3, 8
  inputs = bf.random_lattice(np.random.default_rng(0), num_steps, num_procs, capacity, scale=50.0,
                             mask_prob=0.2)
  log_root, log_op, log_stop, log_cont = _jnp(inputs, jnp.float32)
  log_op = log_op.at[:, :, 0].set(jnp.maximum(log_op[:, :, 0], -5.0))  # keep one path possible
  log_stop = log_stop.at[:, :, 0].set(jnp.maximum(log_stop[:, :, 0], -5.0))
  length = 9_000

  def loglik(*a):
    return php_jax.forward_backward(*a, length=length).log_likelihood

  value, grads = jax.jit(jax.value_and_grad(loglik, argnums=(0, 1, 2, 3)))(log_root, log_op, log_stop,
                                                                            log_cont)
  post = jax.jit(lambda *a: php_jax.forward_backward(*a, length=length))(log_root, log_op, log_stop,
                                                                        log_cont)
  assert np.isfinite(value)
  for g in grads:
    assert np.all(np.isfinite(g))
  assert np.all(np.isfinite(post.v)) and np.all(np.isfinite(post.w))
  np.testing.assert_allclose(post.v[:length].sum(axis=(1, 2)), 1.0, atol=1e-4)
  assert np.all(post.v[length:] == 0)
  # Against float64 on the same inputs.
  with jax.enable_x64(True):
    ref = php_jax.forward_backward(*(jnp.asarray(np.asarray(x), jnp.float64)
                                     for x in (log_root, log_op, log_stop, log_cont)), length=length)
  np.testing.assert_allclose(value, ref.log_likelihood, rtol=1e-5)
  np.testing.assert_allclose(post.v, ref.v, atol=1e-4)


@pytest.mark.parametrize("bad, message", [
    (dict(log_root=np.zeros((4, 3))), "log_root must be"),
    (dict(log_stop=np.zeros((4, 2, 2))), "log_stop must have"),
    (dict(log_op=np.zeros((4, 2))), "log_op must be"),
    (dict(length=5), "length must be in"),
    (dict(length=0), "length must be in"),
])
def test_shape_errors_name_the_argument(bad, message):
  args = dict(log_root=np.zeros((4, 2)), log_op=np.zeros((4, 2, 3)), log_stop=np.zeros((4, 2, 3)),
              log_cont=np.zeros((4, 2, 3)), length=None)
  args.update(bad)
  with pytest.raises(ValueError, match=message):
    php_jax.forward_backward(**args)
