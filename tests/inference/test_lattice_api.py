"""The E-step's wider API against brute-force enumeration: LatticeInputs, top_k, KL and cross-entropy,
tempered and differentiable samples, the forward filter and forward-mode differentiation."""
import pathlib
import runpy

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax.test_util import check_grads

import php_jax
from php_jax.inference import lattice_ops
from tests.inference import lattice_brute_force as bf

# (T, K, C, length): padding, C smaller than T, C larger than T, K = 1, a single step.
CASES = [(5, 2, 3, 5), (6, 2, 2, 4), (4, 3, 5, 4), (3, 1, 3, 3), (1, 2, 2, 1)]


@pytest.fixture(autouse=True)
def float64():
  with jax.enable_x64(True):
    yield


def _lattice(seed, shape, mask_prob=0.0, scale=1.0):
  num_steps, num_procs, capacity, _ = shape
  return bf.random_lattice(np.random.default_rng(seed), num_steps, num_procs, capacity, scale=scale,
                           mask_prob=mask_prob)


def _jnp(inputs):
  return tuple(jnp.asarray(x, jnp.float64) for x in inputs)


def _enumerated_log_probs(inputs, paths, length):
  """log P(ζ, ξ) of every path as a differentiable JAX function of the inputs, [P]."""
  shape = jnp.shape(inputs[1])
  features = bf.path_features(paths, shape, length)
  total = 0.0
  for count, x in zip(features, inputs):
    used = count > 0
    terms = jnp.where(used, count * jnp.where(used, x[None], 0.0), 0.0)
    total = total + jnp.sum(terms.reshape(len(paths), -1), axis=1)
  return total


def _as_path(path_result, i, length):
  procedure, counter = np.asarray(path_result.procedures), np.asarray(path_result.counters)
  return list(zip(procedure[i, :length].tolist(), counter[i, :length].tolist()))


def _as_paths(path_result, length):
  """Every path of a batched LatticePath as a tuple of (h, τ), read once into numpy."""
  procedure, counter = np.asarray(path_result.procedures), np.asarray(path_result.counters)
  return [tuple(zip(h[:length].tolist(), c[:length].tolist())) for h, c in zip(procedure, counter)]


def test_a_paths_old_field_names_still_read_with_a_deprecation_warning():
  path = php_jax.viterbi(php_jax.LatticeInputs(*_jnp(_lattice(0, (5, 2, 3, 4))), length=4))
  with pytest.warns(DeprecationWarning, match="use LatticePath.procedures"):
    np.testing.assert_array_equal(path.procedure, path.procedures)
  with pytest.warns(DeprecationWarning, match="use LatticePath.counters"):
    np.testing.assert_array_equal(path.counter, path.counters)
  assert php_jax.LatticePath._fields == ("procedures", "counters", "log_prob")


def test_lattice_inputs_unpack_into_every_function():
  shape = (5, 2, 3, 4)
  inputs = php_jax.LatticeInputs(*_jnp(_lattice(0, shape)), length=4)
  direct = php_jax.forward_backward(*inputs[:4], length=4)
  np.testing.assert_array_equal(php_jax.forward_backward(*inputs).v, direct.v)
  np.testing.assert_array_equal(php_jax.viterbi(*inputs).procedures, php_jax.viterbi(*inputs[:4], 4).procedures)
  assert php_jax.LatticeInputs(*inputs[:4]).length is None  # length defaults to T


@pytest.mark.parametrize("shape", CASES)
@pytest.mark.parametrize("mask_prob", [0.0, 0.2])
def test_top_k_matches_enumeration(shape, mask_prob):
  length = shape[3]
  inputs = _lattice(1, shape, mask_prob)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, length)
  order = np.argsort(-log_probs, kind="stable")
  possible = int(np.isfinite(log_probs).sum())
  k = possible + 3  # more than there are: the rest is −inf and NO_FRAME
  best = php_jax.top_k(k, *_jnp(inputs), length)
  assert best.procedures.shape == (k, shape[0]) and best.log_prob.shape == (k,)
  np.testing.assert_allclose(best.log_prob[:possible], log_probs[order[:possible]], atol=1e-6)
  assert [_as_path(best, i, length) for i in range(possible)] == [paths[j] for j in order[:possible]]
  assert np.all(np.isneginf(best.log_prob[possible:]))
  assert np.all(np.asarray(best.procedures[possible:]) == php_jax.NO_FRAME)
  assert np.all(np.asarray(best.counters[:, length:]) == php_jax.NO_FRAME)
  viterbi = php_jax.viterbi(*_jnp(inputs), length)
  if possible:
    np.testing.assert_array_equal(best.procedures[0], viterbi.procedures)


def test_top_k_with_ties_returns_distinct_paths_deterministically():
  shape = (4, 2, 3, 4)
  zeros = (np.zeros((4, 2)), np.zeros((4, 2, 3)), np.zeros((4, 2, 3)), np.zeros((4, 2, 3)))
  paths = bf.all_paths(2, 3, 4)
  best = php_jax.top_k(len(paths), *_jnp(zeros))
  got = [tuple(_as_path(best, i, shape[3])) for i in range(len(paths))]
  assert sorted(got) == sorted(tuple(p) for p in paths)  # every path once
  np.testing.assert_array_equal(best.log_prob, 0.0)
  again = php_jax.top_k(len(paths), *_jnp(zeros))
  np.testing.assert_array_equal(again.procedures, best.procedures)
  np.testing.assert_array_equal(again.counters, best.counters)


def test_top_k_under_vmap_with_different_lengths():
  shape = (5, 2, 3, 5)
  batch = [_lattice(s, shape) for s in range(3)]
  stacked = tuple(jnp.asarray(np.stack([b[i] for b in batch])) for i in range(4))
  lengths = jnp.array([5, 2, 4])
  out = jax.vmap(lambda *a: php_jax.top_k(4, *a))(*stacked, lengths)
  for i, b in enumerate(batch):
    single = php_jax.top_k(4, *_jnp(b), int(lengths[i]))
    np.testing.assert_allclose(out.log_prob[i], single.log_prob, atol=1e-9)
    np.testing.assert_array_equal(out.procedures[i], single.procedures)


@pytest.mark.parametrize("shape", CASES[:4])
def test_kl_and_cross_entropy_match_enumeration(shape):
  length = shape[3]
  p_in, q_in = _lattice(2, shape, mask_prob=0.2), _lattice(3, shape)  # q rules out no path p allows
  p_log_z, _, _, paths, p_lp = bf.enumerate_posterior(p_in, length)
  q_log_z, _, _, _, q_lp = bf.enumerate_posterior(q_in, length)
  prob = np.exp(p_lp - p_log_z)
  used = prob > 0
  expected_ce = -np.sum(prob[used] * (q_lp[used] - q_log_z))
  expected_kl = np.sum(prob[used] * ((p_lp[used] - p_log_z) - (q_lp[used] - q_log_z)))
  p, q = php_jax.LatticeInputs(*_jnp(p_in), length), php_jax.LatticeInputs(*_jnp(q_in), length)
  np.testing.assert_allclose(php_jax.cross_entropy(p, q), expected_ce, atol=1e-6)
  np.testing.assert_allclose(php_jax.kl_divergence(p, q), expected_kl, atol=1e-6)
  np.testing.assert_allclose(php_jax.kl_divergence(p, p), 0.0, atol=1e-9)
  # q ruling out a path that p allows: infinite.
  q_cut = q._replace(log_op=q.log_op.at[0, paths[int(np.argmax(p_lp))][0][0], 0].set(-jnp.inf))
  assert php_jax.kl_divergence(p, q_cut) == jnp.inf


def test_kl_and_cross_entropy_gradients_match_enumeration_in_both_arguments():
  shape = (4, 2, 3, 3)
  length = shape[3]
  p_in, q_in = _jnp(_lattice(4, shape)), _jnp(_lattice(5, shape))
  paths = bf.all_paths(shape[1], shape[2], length)

  def enumerated(p, q):
    log_p = jax.nn.log_softmax(_enumerated_log_probs(p, paths, length))
    log_q = jax.nn.log_softmax(_enumerated_log_probs(q, paths, length))
    return jnp.sum(jnp.exp(log_p) * (log_p - log_q)), -jnp.sum(jnp.exp(log_p) * log_q)

  def ours(p, q):
    p, q = php_jax.LatticeInputs(*p, length), php_jax.LatticeInputs(*q, length)
    return php_jax.kl_divergence(p, q), php_jax.cross_entropy(p, q)

  for which in (0, 1):  # KL, then cross-entropy
    expected = jax.grad(lambda p, q: enumerated(p, q)[which], argnums=(0, 1))(p_in, q_in)
    got = jax.grad(lambda p, q: ours(p, q)[which], argnums=(0, 1))(p_in, q_in)
    for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
      np.testing.assert_allclose(g, e, atol=1e-6)


def test_kl_gradients_are_finite_with_masked_cells():
  shape = (5, 2, 3, 5)
  p = php_jax.LatticeInputs(*_jnp(_lattice(6, shape, mask_prob=0.25)), 5)
  q = php_jax.LatticeInputs(*_jnp(_lattice(7, shape)), 5)
  def loss(p_arrays, q_arrays):
    p_in, q_in = php_jax.LatticeInputs(*p_arrays, 5), php_jax.LatticeInputs(*q_arrays, 5)
    return php_jax.kl_divergence(p_in, q_in) + php_jax.cross_entropy(p_in, q_in)

  grads = jax.grad(loss, argnums=(0, 1))(tuple(p[:4]), tuple(q[:4]))
  for g in jax.tree.leaves(grads):
    assert np.all(np.isfinite(g))


def test_a_level_that_cannot_stop_at_some_step_leaves_every_derivative_finite_and_right():
  """top_level's lattice allows no stop before the last step (a zero total of stop weights in the forward
  scan): forward mode, the Hessian, the entropy's and KL's gradients and the forward filter's gradient are
  NaN-free and equal to enumeration's."""
  shape = (4, 1, 5, 4)  # one call of the length's operations, with counters to spare
  length = shape[3]
  root, op, stop, cont = _jnp(_lattice(21, shape))
  inputs = (root, op, php_jax.top_level(stop), cont)
  q_inputs = (root, op + 0.3 * jnp.asarray(np.random.default_rng(5).normal(size=op.shape)), inputs[2], cont)
  every = bf.all_paths(shape[1], shape[2], length)
  possible = np.isfinite(np.asarray(_enumerated_log_probs(inputs, every, length)))
  paths = [path for path, kept in zip(every, possible) if kept]  # the impossible stops' paths left out
  tangents = tuple(jnp.asarray(np.random.default_rng(3).normal(size=x.shape)) for x in inputs)
  for got in jax.jvp(lambda *x: php_jax.forward_backward(*x, length=length), inputs, tangents)[1]:
    assert np.all(np.isfinite(got))
  v_of_op = lambda op: php_jax.forward_backward(inputs[0], op, *inputs[2:], length=length).v
  np.testing.assert_allclose(jax.jacfwd(v_of_op)(inputs[1]), jax.jacrev(v_of_op)(inputs[1]), atol=1e-9)
  log_z = lambda op: jax.nn.logsumexp(_enumerated_log_probs((inputs[0], op, *inputs[2:]), paths, length))
  ours = lambda op: php_jax.forward_backward(inputs[0], op, *inputs[2:], length=length).log_likelihood
  np.testing.assert_allclose(jax.hessian(ours)(inputs[1]), jax.hessian(log_z)(inputs[1]), atol=1e-6)

  def enumerated_kl(p_op):
    log_p = jax.nn.log_softmax(_enumerated_log_probs((inputs[0], p_op, *inputs[2:]), paths, length))
    log_q = jax.nn.log_softmax(_enumerated_log_probs(q_inputs, paths, length))
    return jnp.sum(jnp.exp(log_p) * (log_p - log_q))

  def kl(p_op):
    p = php_jax.LatticeInputs(inputs[0], p_op, *inputs[2:], length)
    return php_jax.kl_divergence(p, php_jax.LatticeInputs(*q_inputs, length))

  np.testing.assert_allclose(jax.grad(kl)(inputs[1]), jax.grad(enumerated_kl)(inputs[1]), atol=1e-6)
  entropy = jax.grad(lambda p_op: php_jax.posterior_entropy(inputs[0], p_op, *inputs[2:], length=length))
  assert np.all(np.isfinite(entropy(inputs[1])))
  prefix = lambda p_op: php_jax.forward_filter(inputs[0], p_op, *inputs[2:], length=length).log_prefix.sum()
  assert np.all(np.isfinite(jax.grad(prefix)(inputs[1])))


def test_where_no_path_explains_the_actions_entropy_kl_and_cross_entropy_are_0_with_finite_gradients():
  """Sums over no paths: 0, not −inf − (−inf)."""
  root, op, stop, cont = _jnp(_lattice(8, (4, 2, 3, 4)))
  never = jnp.full_like(stop, -jnp.inf)  # no frame ever stops: no path
  q = php_jax.LatticeInputs(*_jnp(_lattice(9, (4, 2, 3, 4))), 4)

  def measures(op):
    p = php_jax.LatticeInputs(root, op, never, cont, 4)
    return jnp.stack([php_jax.posterior_entropy(*p), php_jax.kl_divergence(p, q), php_jax.cross_entropy(p, q),
                      php_jax.kl_divergence(p, p)])

  np.testing.assert_array_equal(measures(op), 0.0)
  assert np.all(np.isfinite(jax.jacrev(measures)(op)))


def test_where_no_path_explains_the_actions_viterbi_and_samples_give_no_frame_and_minus_inf():
  """As top_k past the possible paths: no made-up frames."""
  root, op, stop, cont = _jnp(_lattice(8, (4, 2, 3, 4)))
  never = jnp.full_like(stop, -jnp.inf)  # no frame ever stops: no path
  for path in (php_jax.viterbi(root, op, never, cont, 3),
               php_jax.sample_posterior(jax.random.key(0), root, op, never, cont, 3)):
    assert np.isneginf(path.log_prob)
    assert np.all(np.asarray(path.procedures) == php_jax.NO_FRAME)
    assert np.all(np.asarray(path.counters) == php_jax.NO_FRAME)


def test_kl_refuses_different_lengths():
  inputs = _jnp(_lattice(0, (4, 2, 3, 4)))
  with pytest.raises(ValueError, match="same length"):
    php_jax.kl_divergence(php_jax.LatticeInputs(*inputs, 3), php_jax.LatticeInputs(*inputs, 4))


@pytest.mark.parametrize("temperature", [0.5, 3.0])
def test_tempered_posterior_is_the_lattice_divided_by_temperature(temperature):
  shape = (5, 2, 3, 4)
  inputs = _lattice(8, shape, mask_prob=0.1)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, shape[3])
  tempered_prob = np.exp(log_probs / temperature - np.logaddexp.reduce(log_probs / temperature))
  v = np.zeros(shape[:3])
  for prob, path in zip(tempered_prob, paths):
    for t, (h, tau) in enumerate(path):
      v[t, h, tau] += prob
  post = php_jax.forward_backward(*(x / temperature for x in _jnp(inputs)), length=shape[3])
  np.testing.assert_allclose(post.v, v, atol=1e-6)


def test_tempered_samples_match_enumeration():
  shape = (4, 2, 3, 4)
  temperature, num_samples = 2.5, 20_000
  inputs = _lattice(9, shape)
  _, _, _, paths, log_probs = bf.enumerate_posterior(inputs, shape[3])
  probs = np.exp(log_probs / temperature - np.logaddexp.reduce(log_probs / temperature))
  keys = jax.random.split(jax.random.key(1), num_samples)
  samples = jax.jit(jax.vmap(lambda k: php_jax.sample_posterior(k, *_jnp(inputs), 4, temperature=temperature)))(keys)
  index = {tuple(p): i for i, p in enumerate(paths)}
  counts = np.zeros(len(paths))
  for path in _as_paths(samples, 4):
    counts[index[path]] += 1
  sigma = np.sqrt(probs * (1 - probs) / num_samples)
  assert np.all(np.abs(counts / num_samples - probs) <= 5 * sigma + 1e-9)
  # log_prob stays the untempered complete-data log-likelihood.
  np.testing.assert_allclose(samples.log_prob[0], log_probs[index[tuple(_as_path(samples, 0, 4))]], atol=1e-9)


def test_temperature_one_gives_todays_samples():
  inputs = _jnp(_lattice(10, (6, 2, 3, 5)))
  key = jax.random.key(3)
  default = php_jax.sample_posterior(key, *inputs, 5)
  explicit = php_jax.sample_posterior(key, *inputs, 5, temperature=1.0)
  for a, b in zip(default, explicit):
    np.testing.assert_array_equal(a, b)


def test_straight_through_sample_gradient_is_that_of_its_exact_expectation():
  temperature = 0.7
  shape = (5, 2, 3, 4)
  length = shape[3]
  inputs = _jnp(_lattice(11, shape))
  paths = bf.all_paths(shape[1], shape[2], length)
  weights = jnp.asarray(np.random.default_rng(0).normal(size=shape[:3]))
  cells = jnp.asarray(bf.path_features(paths, shape[:3], length)[1])  # [P, T, K, C] frame indicators

  def expectation(*x):  # E[Σ weights · z] under the tempered posterior, by enumeration
    probs = jax.nn.softmax(_enumerated_log_probs(x, paths, length) / temperature)
    return jnp.sum(probs * jnp.sum(cells * weights, axis=(1, 2, 3)))

  def sampled(*x):
    return jnp.sum(weights * php_jax.differentiable_sample(jax.random.key(5), *x, length, temperature))

  expected = jax.grad(expectation, argnums=(0, 1, 2, 3))(*inputs)
  got = jax.grad(sampled, argnums=(0, 1, 2, 3))(*inputs)
  for g, e in zip(got, expected):
    np.testing.assert_allclose(g, e, atol=1e-6)
  # The value is one valid path's frame indicators, and their mean over many keys is the marginals v.
  keys = jax.random.split(jax.random.key(6), 2000)
  z = jax.jit(jax.vmap(lambda k: php_jax.differentiable_sample(k, *inputs, length, temperature)))(keys)
  np.testing.assert_allclose(z.sum(axis=(2, 3)), np.tile([1.0] * length + [0.0], (2000, 1)), atol=1e-12)
  assert tuple(zip(*np.nonzero(np.asarray(z[0]).round()))) in {
      tuple((t, h, tau) for t, (h, tau) in enumerate(p)) for p in paths}
  v = php_jax.forward_backward(*(x / temperature for x in inputs), length=length).v
  assert np.all(np.abs(z.mean(axis=0) - v) <= 5 * np.sqrt(v * (1 - v) / 2000) + 1e-9)


def test_perturb_and_marginals_approaches_perturb_and_map_and_is_smooth():
  shape = (5, 2, 3, 4)
  inputs = _jnp(_lattice(12, shape))
  key = jax.random.key(7)
  relaxed = php_jax.differentiable_sample(key, *inputs, 4, temperature=1e-3, method="perturb-and-marginals")
  perturbed_map = php_jax.viterbi(*lattice_ops.perturb(key, *inputs), 4)
  np.testing.assert_allclose(relaxed, lattice_ops.frame_indicators(perturbed_map, shape[:3]), atol=1e-6)
  weights = jnp.asarray(np.random.default_rng(1).normal(size=shape[:3]))
  check_grads(lambda *x: jnp.sum(weights * php_jax.differentiable_sample(
      key, *x, 4, temperature=0.8, method="perturb-and-marginals")), inputs, order=1, modes=["rev"],
              atol=1e-5, rtol=1e-5)


@pytest.mark.parametrize("shape", CASES)
@pytest.mark.parametrize("mask_prob", [0.0, 0.2])
def test_forward_filter_matches_enumerated_prefixes(shape, mask_prob):
  num_steps, num_procs, capacity, length = shape
  inputs = _lattice(13, shape, mask_prob)
  log_z = bf.enumerate_posterior(inputs, length)[0]
  filt = php_jax.forward_filter(*_jnp(inputs), length)
  np.testing.assert_allclose(filt.log_likelihood, log_z, atol=1e-6)
  for t in range(length):
    prefixes = bf.all_paths(num_procs, capacity, t + 1)
    log_probs = np.array([bf.prefix_log_prob(inputs, p) for p in prefixes])
    log_prefix = np.logaddexp.reduce(log_probs)
    np.testing.assert_allclose(filt.log_prefix[t], log_prefix, atol=1e-6)
    filtered = np.zeros((num_procs, capacity))
    if np.isfinite(log_prefix):
      for lp, p in zip(log_probs, prefixes):
        filtered[p[-1]] += np.exp(lp - log_prefix)
    np.testing.assert_allclose(filt.filtered[t], filtered, atol=1e-6)
  np.testing.assert_array_equal(filt.log_prefix[length:], 0.0)
  np.testing.assert_array_equal(filt.filtered[length:], 0.0)
  if np.isfinite(log_z):  # the docstring's identity between the filter and log P(ξ)
    last = filt.log_prefix[length - 1] + jnp.log(jnp.sum(filt.filtered[length - 1] * jnp.exp(inputs[2][length - 1])))
    np.testing.assert_allclose(last, log_z, atol=1e-6)


def test_forward_mode_matches_finite_differences_and_the_enumerated_hessian():
  shape = (4, 2, 3, 3)
  length = shape[3]
  inputs = _jnp(_lattice(14, shape))
  weights = jnp.asarray(np.random.default_rng(2).normal(size=shape[:3]))

  def loss(*x):  # the log-likelihood rule and the marginals' tangents
    post = php_jax.forward_backward(*x, length=length)
    return post.log_likelihood + jnp.sum(weights * post.v) + jnp.sum(weights ** 2 * post.w)

  check_grads(loss, inputs, order=1, modes=["fwd", "rev"], atol=1e-5, rtol=1e-5)
  check_grads(loss, inputs, order=2, modes=["fwd"], atol=1e-5, rtol=1e-5)
  v_of_op = lambda op: php_jax.forward_backward(inputs[0], op, *inputs[2:], length=length).v
  np.testing.assert_allclose(jax.jit(jax.jacfwd(v_of_op))(inputs[1]), jax.jit(jax.jacrev(v_of_op))(inputs[1]),
                             atol=1e-9)
  paths = bf.all_paths(shape[1], shape[2], length)
  log_z = lambda *x: jax.nn.logsumexp(_enumerated_log_probs(x, paths, length))
  ours = lambda *x: php_jax.forward_backward(*x, length=length).log_likelihood
  expected = jax.jit(jax.hessian(log_z, argnums=(0, 1, 2, 3)))(*inputs)
  got = jax.jit(jax.hessian(ours, argnums=(0, 1, 2, 3)))(*inputs)
  for g, e in zip(jax.tree.leaves(got), jax.tree.leaves(expected)):
    np.testing.assert_allclose(g, e, atol=1e-6)
  tangents = tuple(jnp.asarray(np.random.default_rng(3).normal(size=x.shape)) for x in inputs)
  _, jvp = jax.jvp(ours, inputs, tangents)
  grads = jax.grad(ours, argnums=(0, 1, 2, 3))(*inputs)
  np.testing.assert_allclose(jvp, sum(jnp.sum(g * d) for g, d in zip(grads, tangents)), atol=1e-9)


def test_example_runs(capsys):
  runpy.run_path(str(pathlib.Path(__file__).parents[2] / "examples" / "estep_operations.py"),
                 run_name="__main__")
  assert "top_k" in capsys.readouterr().out


def test_annotate_refuses_out_of_range_concrete_annotations_naming_the_step():
  log_op = jnp.zeros((4, 2, 3))
  ok = php_jax.annotate(log_op, np.array([0, -1, 1, -1]), np.array([0, 1, -1, 2]))
  assert ok.shape == log_op.shape
  with pytest.raises(ValueError, match=r"procedure\[2\] = 2"):
    php_jax.annotate(log_op, np.array([0, 1, 2, 0]), np.array([-1, -1, -1, -1]))
  with pytest.raises(ValueError, match=r"counter\[1\] = -2"):
    php_jax.annotate(log_op, jnp.array([0, 1, 1, 0]), jnp.array([0, -2, 0, 0]))
  with pytest.raises(ValueError, match=r"counter\[3\] = 3"):
    php_jax.annotate(log_op, [-1, -1, -1, -1], [0, 1, 2, 3])
  # Traced annotations are not checked (no error inside jit).
  traced = jax.jit(php_jax.annotate)(log_op, jnp.array([0, 1, 2, 0]), jnp.array([0, 0, 0, 0]))
  assert traced.shape == log_op.shape


def _valid_arrays():
  return dict(log_root=np.zeros((4, 2)), log_op=np.zeros((4, 2, 3)), log_stop=np.full((4, 2, 3), -np.inf),
              log_cont=np.zeros((4, 2, 3), np.float32))


@pytest.mark.parametrize("length", [None, 1, 4, np.int64(3), np.array(2), jnp.array(4, jnp.int32)])
def test_validate_inputs_accepts_valid_lattices(length):
  inputs = php_jax.validate_inputs(**_valid_arrays(), length=length)
  assert isinstance(inputs, php_jax.LatticeInputs)
  assert inputs.length == (4 if length is None else int(length)) and isinstance(inputs.length, int)


@pytest.mark.parametrize("bad, message", [
    (dict(log_op=np.zeros((4, 2, 3), np.int32)), "log_op must be a float array; got dtype int32"),
    (dict(log_root=[[0.0, 0.0]] * 4), "log_root must be a float array; got a list"),
    (dict(log_stop=np.zeros((4, 3, 3))), "log_stop must have"),
    (dict(log_root=np.zeros((4, 0)), log_op=np.zeros((4, 0, 3)), log_stop=np.zeros((4, 0, 3)),
          log_cont=np.zeros((4, 0, 3))), "must be ≥ 1"),
    (dict(log_cont=np.where(np.arange(24).reshape(4, 2, 3) == 5, np.nan, 0.0)), r"log_cont contains NaN at index \(0, 1, 2\)"),
    (dict(log_op=np.where(np.arange(24).reshape(4, 2, 3) == 7, np.inf, 0.0)), r"log_op contains \+inf"),
    (dict(length=0), "length must be in 1..T"),
    (dict(length=np.int32(5)), "length must be in 1..T"),
    (dict(length=2.0), "length must be an integer"),
    (dict(length=True), "length must be an integer"),
    (dict(length=np.array([2])), "length must be an integer"),
])
def test_validate_inputs_refuses_with_a_clear_message(bad, message):
  args = _valid_arrays()
  args.update(bad)
  with pytest.raises(ValueError, match=message):
    php_jax.validate_inputs(**args)


def test_validate_inputs_refuses_traced_values():
  with pytest.raises(TypeError, match="traced"):
    jax.jit(lambda x: php_jax.validate_inputs(x, *list(_valid_arrays().values())[1:]))(np.zeros((4, 2)))


def test_the_forward_filter_in_float32_on_a_long_trace_is_as_close_to_float64_as_the_smoother():
  """T = 10,000: the filter's running log-scale is a sum of 10,000 float32 terms, compensated (Kahan) so
  that its log P(ξ) and log-prefixes err no more than forward_backward's whole-trace sum."""
  inputs = bf.random_lattice(np.random.default_rng(0), 10_000, 3, 4, scale=5.0)
  exact = php_jax.forward_backward(*_jnp(inputs)).log_likelihood  # float64 (the module's fixture)
  single = [jnp.asarray(x, jnp.float32) for x in inputs]
  filtered = lattice_ops.forward_filter(*single)
  smoother_error = abs(float(php_jax.forward_backward(*single).log_likelihood) - float(exact))
  assert abs(float(filtered.log_likelihood) - float(exact)) <= max(2 * smoother_error, 2e-3)
  prefix = lattice_ops.forward_filter(*_jnp(inputs)).log_prefix
  assert float(jnp.max(jnp.abs(filtered.log_prefix - prefix))) < 5e-3


@pytest.mark.parametrize("dtype", [jnp.float16, jnp.bfloat16])
def test_half_precision_inputs_are_computed_in_float32(dtype):
  """T = 10,000 with ×50 logits: log P(ξ) ≈ −66,000 is beyond float16's range (−65,504), so a float16
  computation gave −inf. Half-precision inputs are computed in float32: finite results in float32, equal to
  float32 on the same (rounded) inputs and close to it on the unrounded ones; gradients in the input dtype."""
  inputs = bf.random_lattice(np.random.default_rng(0), 10_000, 3, 8, scale=50.0, mask_prob=0.2)
  full = [jnp.asarray(x, jnp.float32) for x in inputs]
  for i in (1, 2):  # keep one path possible
    full[i] = full[i].at[:, :, 0].set(jnp.maximum(full[i][:, :, 0], -5.0))
  half = [x.astype(dtype) for x in full]
  rounded = [x.astype(jnp.float32) for x in half]
  length = 9_000

  def loglik(*a):
    return php_jax.forward_backward(*a, length=length).log_likelihood

  value, grads = jax.jit(jax.value_and_grad(loglik, argnums=(0, 1, 2, 3)))(*half)
  expected = jax.jit(loglik)(*full)
  assert value.dtype == jnp.float32 and np.isfinite(value) and expected < np.finfo(np.float16).min
  np.testing.assert_allclose(value, jax.jit(loglik)(*rounded), rtol=1e-6)
  np.testing.assert_allclose(value, expected, rtol=1e-4)
  assert [g.dtype for g in grads] == [jnp.dtype(dtype)] * 4
  assert all(np.all(np.isfinite(np.asarray(g, np.float32))) for g in grads)
  v = php_jax.forward_backward(*rounded, length=length).v  # ∂ log P / ∂ log_op = v, rounded to the input dtype
  np.testing.assert_allclose(np.asarray(grads[1], np.float32), v, atol=1e-2)
  for result in (php_jax.viterbi(*half, length=length).log_prob,
                 lattice_ops.forward_filter(*half, length=length).log_likelihood,
                 lattice_ops.top_k(2, *half, length=length).log_prob,
                 php_jax.sample_posterior(jax.random.key(0), *half, length=length).log_prob,
                 php_jax.kl_divergence(php_jax.LatticeInputs(*half, length), php_jax.LatticeInputs(*full, length))):
    assert result.dtype == jnp.float32 and np.all(np.isfinite(result)), result


def test_every_function_takes_one_lattice_inputs_in_place_of_the_five_arrays():
  """The arguments after a LatticeInputs fill the function's other parameters in order; bit for bit."""
  inputs = php_jax.LatticeInputs(*_jnp(_lattice(0, (5, 2, 3, 4))), length=4)
  key, procedure, counter = jax.random.key(1), np.array([0, 0, 1, 1, -1]), np.array([0, 1, 0, 1, -1])
  pairs = [(php_jax.forward_backward(inputs), php_jax.forward_backward(*inputs)),
           (php_jax.viterbi(inputs), php_jax.viterbi(*inputs)),
           (php_jax.sample_posterior(key, inputs, 0.5), php_jax.sample_posterior(key, *inputs, 0.5)),
           (php_jax.top_k(3, inputs), php_jax.top_k(3, *inputs)),
           (php_jax.complete_log_likelihood(inputs, procedure, counter),
            php_jax.complete_log_likelihood(*inputs[:4], procedure, counter, 4)),
           (php_jax.posterior_entropy(inputs), php_jax.posterior_entropy(*inputs)),
           (php_jax.forward_filter(inputs), php_jax.forward_filter(*inputs)),
           (php_jax.differentiable_sample(key, inputs), php_jax.differentiable_sample(key, *inputs)),
           (php_jax.validate_inputs(inputs), php_jax.validate_inputs(*inputs))]
  for got, want in pairs:
    assert type(got) is type(want)
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
      np.testing.assert_array_equal(g, w)
  with pytest.raises(TypeError, match="length"):
    php_jax.forward_backward(inputs, length=4)
  with pytest.raises(TypeError, match=r"at most 2 positional arguments after a LatticeInputs \(procedures, counters\)"):
    php_jax.forward_backward(inputs, procedure, counter, 1)


def test_annotation_arguments_are_annotate_and_results_speak_the_stack_names():
  """procedures=, counters= are annotate's mask (padding ignored); v is `marginals`, a path's procedure and
  counter are `procedures`, `counters`, and feeding them back gives the path's complete-data likelihood."""
  inputs = php_jax.LatticeInputs(*_jnp(_lattice(1, (5, 2, 3, 4))), length=4)
  procedures, counters = np.array([1, -1, -1, 0, 7]), np.array([0, -1, 2, -1, 9])  # step 4 is padding
  used = np.arange(5) < 4
  masked = inputs._replace(log_op=php_jax.annotate(inputs.log_op, np.where(used, procedures, -1),
                                                   np.where(used, counters, -1)))
  only_counters = inputs._replace(log_op=php_jax.annotate(inputs.log_op, -np.ones(5, int),
                                                          np.where(used, counters, -1)))
  key = jax.random.key(2)
  pairs = [(php_jax.forward_backward(inputs, procedures, counters), php_jax.forward_backward(masked)),
           (php_jax.viterbi(inputs, procedures=procedures, counters=counters), php_jax.viterbi(masked)),
           (php_jax.top_k(2, inputs, procedures, counters), php_jax.top_k(2, masked)),
           (php_jax.sample_posterior(key, inputs, procedures=procedures, counters=counters),
            php_jax.sample_posterior(key, masked)),
           (php_jax.posterior_entropy(inputs, counters=counters), php_jax.posterior_entropy(only_counters))]
  for got, want in pairs:
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
      np.testing.assert_array_equal(g, w)
  assert np.isfinite(pairs[0][0].log_likelihood)
  post, path = php_jax.forward_backward(inputs), php_jax.viterbi(inputs)
  assert post.marginals is post.v and path.procedures is path.procedures and path.counters is path.counters
  np.testing.assert_allclose(php_jax.forward_backward(inputs, path.procedures, path.counters).log_likelihood,
                             path.log_prob, atol=1e-12)


def test_two_level_lattice_structure_matches_enumeration_and_passes_through_jit_and_vmap():
  shape, length = (5, 2, 3, 4), 4
  p_arrays, q_arrays = _lattice(4, shape, mask_prob=0.2), _lattice(3, shape)
  log_z, v, _, paths, log_probs = bf.enumerate_posterior(p_arrays, length)
  q_log_probs = bf.enumerate_posterior(q_arrays, length)[4]
  p_inputs, q_inputs = (php_jax.LatticeInputs(*_jnp(x), length) for x in (p_arrays, q_arrays))
  p, q = php_jax.TwoLevelLattice(p_inputs), php_jax.TwoLevelLattice(q_inputs)
  order = np.argsort(-log_probs, kind="stable")
  entropy, cross = bf.entropy(log_probs, log_z), bf.cross_entropy(log_probs, q_log_probs)
  np.testing.assert_allclose(p.log_partition(), log_z, atol=1e-9)
  np.testing.assert_allclose(p.marginals(), v, atol=1e-9)
  np.testing.assert_allclose(p.posterior().v, v, atol=1e-9)
  assert _as_paths(jax.tree.map(lambda x: x[None], p.argmax()), length) == [tuple(paths[order[0]])]
  np.testing.assert_allclose(p.top_k(3).log_prob, log_probs[order[:3]], atol=1e-9)
  np.testing.assert_allclose([p.entropy(), p.cross_entropy(q), p.kl_divergence(q)],
                             [entropy, cross, cross - entropy], atol=1e-9)
  key = jax.random.key(4)
  for got, want in zip(p.sample(key, 0.5), php_jax.sample_posterior(key, p_inputs, temperature=0.5)):
    np.testing.assert_array_equal(got, want)
  # Restricted to an annotation (the most likely path's procedure at step 1): the agreeing paths only; +inf
  # where q rules out a path p allows.
  known = paths[order[0]][1][0]
  procedures = np.array([-1, known, -1, -1, -1])
  agree = np.array([path[1][0] == known for path in paths])
  p_known, q_known = (php_jax.TwoLevelLattice(x, procedures=procedures) for x in (p_inputs, q_inputs))
  sub, sub_q = log_probs[agree], q_log_probs[agree]
  assert 1 < np.isfinite(sub).sum() < np.isfinite(log_probs).sum()
  entropy, cross = bf.entropy(sub, np.logaddexp.reduce(sub)), bf.cross_entropy(sub, sub_q)
  np.testing.assert_allclose([p_known.log_partition(), p_known.entropy(), p_known.kl_divergence(q_known)],
                             [np.logaddexp.reduce(sub), entropy, cross - entropy], atol=1e-9)
  assert p.kl_divergence(q_known) == np.inf
  # A pytree: built inside vmap, queried under jit and vmap.
  lattices = jax.vmap(php_jax.TwoLevelLattice)(jax.tree.map(lambda *x: jnp.stack(x), p_inputs, q_inputs))
  entropies = jax.jit(jax.vmap(lambda s: s.entropy()))(lattices)
  assert isinstance(lattices, php_jax.TwoLevelLattice)
  np.testing.assert_allclose(entropies, [p.entropy(), q.entropy()], atol=1e-9)


def _zeros_lattice():
  return (jnp.zeros((4, 2)), jnp.zeros((4, 2, 3)), jnp.full((4, 2, 3), -0.5), jnp.full((4, 2, 3), -1.0))


_KEY = jax.random.key(0)


@pytest.mark.parametrize("call, message", [
    (lambda x: php_jax.forward_backward(*x, length=2.5), r"length must be an integer in 1..T = 1..4; got 2.5"),
    (lambda x: php_jax.viterbi(*x, length=True), r"length must be an integer in 1..T = 1..4; got True"),
    (lambda x: php_jax.top_k(2, *x, np.float32(3)), "length must be an integer in 1..T = 1..4"),
    (lambda x: php_jax.forward_filter(*x, jnp.array([2, 3])),
     r"length must be an integer .*got an array of shape \(2,\)"),
    (lambda x: php_jax.posterior_entropy(*x, 5), r"length must be in 1..T = 1..4; got 5"),
    (lambda x: php_jax.forward_backward(*x, length=jnp.array(0)), r"length must be in 1..T = 1..4; got 0"),
    (lambda x: php_jax.sample_posterior(_KEY, *x, temperature=0), "temperature must be a finite number > 0; got 0"),
    (lambda x: php_jax.sample_posterior(_KEY, *x, temperature=-1.0), "temperature must be a finite number > 0"),
    (lambda x: php_jax.sample_posterior(_KEY, *x, temperature=np.inf), "temperature must be a finite number > 0"),
    (lambda x: php_jax.sample_posterior(_KEY, *x, temperature=np.nan), "temperature must be a finite number > 0"),
    (lambda x: php_jax.sample_posterior(_KEY, *x, temperature=True), "temperature must be a finite number > 0"),
    (lambda x: php_jax.differentiable_sample(_KEY, *x, temperature=jnp.ones(2)), r"temperature .*shape \(2,\)"),
    (lambda x: php_jax.annotate(x[1], np.array([0.0, 1.0, 1.0, 0.0]), np.zeros(4, int)),
     "procedure must be an integer array"),
    (lambda x: php_jax.annotate(x[1], np.zeros((4, 2), int), np.zeros(4, int)),
     r"procedure must have shape \(4,\); got \(4, 2\)"),
    (lambda x: php_jax.complete_log_likelihood(*x, np.array([2, 0, 0, 0]), np.array([0, 1, 2, 0])),
     r"procedure\[0\] = 2 is outside −1..K−1 = −1..1"),
    (lambda x: php_jax.complete_log_likelihood(*x, np.zeros(4, int), np.array([0, 1, 2, 3])),
     r"counter\[3\] = 3 is outside −1..C−1 = −1..2"),
    (lambda x: php_jax.forward_backward(*x, procedures=np.array([0, 0, 0, 2])), r"procedures\[3\] = 2"),
    (lambda x: php_jax.viterbi(*x, counters=np.zeros(5, np.int32)), r"counters must have shape \(4,\); got \(5,\)"),
    (lambda x: php_jax.top_k(True, *x), "k must be an int ≥ 1; got True"),
    (lambda x: php_jax.kl_divergence(php_jax.LatticeInputs(*x, 3), php_jax.LatticeInputs(*x, 2.5)),
     "q: length must be an integer"),
    (lambda x: php_jax.TwoLevelLattice(php_jax.LatticeInputs(*x), procedures=np.ones(4)),
     "procedures must be an integer array"),
    (lambda x: php_jax.TwoLevelLattice(php_jax.LatticeInputs(*x, 0)), r"length must be in 1..T"),
    (lambda x: php_jax.TwoLevelLattice(php_jax.LatticeInputs(*x)).sample(_KEY, 0.0), "temperature"),
    (lambda x: php_jax.TwoLevelLattice(php_jax.LatticeInputs(*x)).kl_divergence(php_jax.LatticeInputs(*x)),
     "other must be a TwoLevelLattice; got a LatticeInputs"),
])
def test_refusals_name_the_argument(call, message):
  with pytest.raises(ValueError, match=message):
    call(_zeros_lattice())


def test_what_is_not_refused():
  """Annotation values on padding are ignored; traced ones are not range-checked (out of range matches
  nothing); arrays of different float dtypes are computed in the promoted one."""
  x = _zeros_lattice()
  np.testing.assert_array_equal(php_jax.forward_backward(*x, 2, procedures=np.array([0, 0, 7, 7])).log_likelihood,
                                php_jax.forward_backward(*x, 2, procedures=np.array([0, 0, -1, -1])).log_likelihood)
  traced = jax.jit(lambda p: php_jax.forward_backward(*x, procedures=p).log_likelihood)(np.array([0, 0, 0, 2]))
  assert traced == -np.inf
  mixed = php_jax.forward_backward(x[0].astype(jnp.float32), *(a.astype(jnp.float64) for a in x[1:]))
  assert mixed.v.dtype == jnp.float64
  np.testing.assert_array_equal(mixed.v, php_jax.forward_backward(*(a.astype(jnp.float64) for a in x)).v)
