"""Whole-stack E-step against brute-force enumeration of stack trajectories, the two-level lattice, the EG
identities, annotation, decoding, sampling, padding, batching and long-trace numerics."""
import collections
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import php_jax
from php_jax.inference import stack_lattice as sl
from tests.inference import lattice_brute_force as bf

# (K, C, T): three levels with padding room, and four levels.
THREE = ((1, 2, 2), (3, 3, 2), 6)
FOUR = ((1, 2, 1, 2), (2, 2, 2, 2), 4)
# (shape, length, mask probability): padding (with garbage in it), −inf masks, a single step.
CASES = [(THREE, 6, 0.0), (THREE, 4, 0.15), (THREE, 1, 0.0), (FOUR, 4, 0.15), (FOUR, 3, 0.0)]


def random_stack(rng, sizes, capacities, num_steps, scale=1.0, mask_prob=0.0, length=None):
  """Random normalised log-probabilities as a StackInputs, optionally −inf-masked; steps ≥ length (padding)
  hold garbage: large, small and −inf values."""
  def log_softmax(x):
    x = x - x.max(axis=-1, keepdims=True)
    return x - np.log(np.exp(x).sum(axis=-1, keepdims=True))

  def masked(x):
    return np.where(rng.uniform(size=x.shape) < mask_prob, -np.inf, x)

  frames = [(num_steps, k, c) for k, c in zip(sizes, capacities)]
  log_call = tuple(masked(log_softmax(scale * rng.normal(size=f + (k,)))) for f, k in zip(frames, sizes[1:]))
  log_act = masked(np.log(rng.uniform(0.05, 1.0, size=frames[-1])) * scale)
  z = [scale * rng.normal(size=f) for f in frames]
  log_stop = tuple(masked(-np.logaddexp(0, -x)) for x in z)
  log_cont = tuple(-np.logaddexp(0, x) for x in z)
  fields = (log_call, log_act, log_stop, log_cont)
  if length is not None:
    fields = jax.tree.map(lambda x: np.where(np.arange(num_steps).reshape((-1,) + (1,) * (x.ndim - 1)) < length, x,
                                             rng.choice([-np.inf, 30.0, -5.0], x.shape)), fields)
  return sl.StackInputs(*fields, length=length)


def event_posteriors(inputs, length, probs, stacks):
  """Enumerated posteriors, by step and frame, of the events each input is consulted on.

  A frame stays at τ = 0 while the levels below it run, so level k was pushed at t iff every level ≥ k has
  τ = 0 at t, and every level below i stopped at t iff every level > i has τ = 0 at t+1.

  Returns dict: marginals[i] [T, K_i, C_i]; call[i] [T, K_i, C_i, K_{i+1}] P(level i at (h, τ) pushes h' at
  t); stop[i], cont[i] [T, K_i, C_i] P(level i at (h, τ), every level below stops, level i stops / continues).
  """
  depth = len(inputs.log_stop)
  events = {name: [np.zeros(x.shape) for x in arrays] for name, arrays in
            (("marginals", inputs.log_stop), ("call", inputs.log_call), ("stop", inputs.log_stop),
             ("cont", inputs.log_stop))}
  for p, stack in zip(probs, stacks):
    for t, frames in enumerate(stack):
      last = t == length - 1
      for i, (h, tau) in enumerate(frames):
        events["marginals"][i][t, h, tau] += p
        if i < depth - 1 and all(frames[k][1] == 0 for k in range(i + 1, depth)):
          events["call"][i][t, h, tau, frames[i + 1][0]] += p
        nxt = None if last else stack[t + 1]
        below_stop = last or all(nxt[k][1] == 0 for k in range(i + 1, depth))
        if below_stop and (last or nxt[i][1] == 0):
          events["stop"][i][t, h, tau] += p
        elif below_stop:
          events["cont"][i][t, h, tau] += p
  return events


def _jnp(inputs, dtype):
  return sl.StackInputs(*jax.tree.map(lambda x: jnp.asarray(x, dtype), tuple(inputs[:4])), length=inputs.length)


@jax.jit
def _posterior_and_grads(inputs, procedures, counters):
  """forward_backward and jax.grad of its log_likelihood with respect to the four log-probability fields."""
  def log_likelihood(fields):
    post = sl.forward_backward(sl.StackInputs(*fields, length=inputs.length), procedures, counters)
    return post.log_likelihood, post
  (_, post), grads = jax.value_and_grad(log_likelihood, has_aux=True)(tuple(inputs[:4]))
  return post, sl.StackInputs(*grads)


def posterior_and_grads(inputs, procedures=None, counters=None):
  """One compiled function per shape for every test (unknown annotations are passed as −1 arrays); numpy out."""
  unknown = np.full((inputs.log_act.shape[0], len(inputs.log_stop)), -1, np.int32)
  return jax.device_get(_posterior_and_grads(inputs, unknown if procedures is None else procedures,
                              unknown if counters is None else counters))


KEYS = jax.random.split(jax.random.key(0), 4000)
_sample_many = jax.jit(jax.vmap(sl.sample_posterior, (0, None, None, None, None)))


def sample_many(inputs, procedures=None, counters=None, temperature=1.0):
  """sample_posterior for each of KEYS, compiled once per shape like posterior_and_grads; numpy out."""
  unknown = np.full((inputs.log_act.shape[0], len(inputs.log_stop)), -1, np.int32)
  return jax.device_get(_sample_many(KEYS, inputs, unknown if procedures is None else procedures,
                                     unknown if counters is None else counters, temperature))


def _annotation(stack, num_steps):
  """[T, d] procedures and counters of an enumerated path, −1 on padding."""
  depth = len(stack[0])
  procedures = np.full((num_steps, depth), -1, np.int32)
  counters = np.full((num_steps, depth), -1, np.int32)
  for t, frames in enumerate(stack):
    procedures[t], counters[t] = zip(*frames)
  return procedures, counters


def _case(case, seed, scale=1.0):
  """A CASES entry drawn with the first seed from `seed` on whose demonstration has a possible path:
  (inputs as float64 numpy, the same as jax arrays, T, d, bf.stack_posterior(inputs, length))."""
  (sizes, capacities, num_steps), length, mask_prob = case
  while True:
    inputs = random_stack(np.random.default_rng(seed), sizes, capacities, num_steps, scale, mask_prob, length)
    enumerated = bf.stack_posterior(inputs, length)
    if np.isfinite(enumerated[0]):
      return inputs, _jnp(inputs, jnp.float64), num_steps, len(sizes), enumerated
    seed += 1000


@pytest.mark.parametrize("case", CASES)
def test_forward_backward_and_eg_identities_match_enumeration(case):
  with jax.enable_x64(True):
    inputs, args, _, depth, (log_z, probs, stacks, _) = _case(case, seed=len(str(case)))
    events = event_posteriors(inputs, inputs.length, probs, stacks)
    post, grads = posterior_and_grads(args)
  np.testing.assert_allclose(post.log_likelihood, log_z, atol=1e-6)
  for got, want in zip(post.marginals, events["marginals"]):
    np.testing.assert_allclose(got, want, atol=1e-6)
  assert all(np.isfinite(g).all() for g in jax.tree.leaves(grads))
  # jax.grad of log P(ξ) is the posterior of the event each input is consulted on.
  np.testing.assert_allclose(grads.log_act, post.marginals[-1], atol=1e-6)
  for i in range(depth - 1):
    np.testing.assert_allclose(grads.log_call[i], events["call"][i], atol=1e-6)
  for i in range(depth):
    np.testing.assert_allclose(grads.log_stop[i], events["stop"][i], atol=1e-6)
    np.testing.assert_allclose(grads.log_cont[i], events["cont"][i], atol=1e-6)
  # Level i's termination is consulted exactly when every level below it stops: for the lowest level always.
  np.testing.assert_allclose(grads.log_stop[-1] + grads.log_cont[-1], post.marginals[-1], atol=1e-6)
  assert (grads.log_stop[0] + grads.log_cont[0] <= post.marginals[0] + 1e-9).all()


@pytest.mark.parametrize("case", CASES)
def test_viterbi_matches_enumeration(case):
  with jax.enable_x64(True):
    inputs, args, num_steps, _, (_, _, stacks, log_probs) = _case(case, seed=3)
    path = sl.viterbi(args)
  best = int(np.argmax(log_probs))
  want_procedures, want_counters = _annotation(stacks[best], num_steps)
  np.testing.assert_array_equal(path.procedures, want_procedures)
  np.testing.assert_array_equal(path.counters, want_counters)
  np.testing.assert_allclose(path.log_prob, log_probs[best], atol=1e-6)


def test_annotation_full_and_partial():
  rng = np.random.default_rng(11)
  with jax.enable_x64(True):
    inputs, args, num_steps, _, (_, probs, stacks, log_probs) = _case((THREE, 5, 0.0), seed=11)
    length = inputs.length
    for index in rng.choice(len(stacks), 3, p=probs):  # full annotation: the complete-data log-likelihood
      procedures, counters = _annotation(stacks[index], num_steps)
      post, _ = posterior_and_grads(args, procedures, counters)
      np.testing.assert_allclose(post.log_likelihood, log_probs[index], atol=1e-6)
      for i, marginal in enumerate(post.marginals):
        np.testing.assert_allclose(marginal[np.arange(length), procedures[:length, i], counters[:length, i]], 1.0,
                                   atol=1e-6)
    # Partial annotation: each entry of a path known with probability 1/2, per step and level.
    procedures, counters = _annotation(stacks[int(np.argmax(probs))], num_steps)
    procedures = np.where(rng.uniform(size=procedures.shape) < 0.5, procedures, -1)
    counters = np.where(rng.uniform(size=counters.shape) < 0.5, counters, -1)

    def agrees(stack, counters=counters):
      return all((procedures[t, i] < 0 or procedures[t, i] == h) and (counters[t, i] < 0 or counters[t, i] == tau)
                 for t, frames in enumerate(stack) for i, (h, tau) in enumerate(frames))

    log_z, sub_probs, sub_stacks, sub_log_probs = bf.stack_posterior(inputs, length, agrees)
    assert 1 < len(sub_stacks) < len(stacks)
    post, _ = posterior_and_grads(args, procedures, counters)
    np.testing.assert_allclose(post.log_likelihood, log_z, atol=1e-6)
    for got, want in zip(post.marginals, event_posteriors(inputs, length, sub_probs, sub_stacks)["marginals"]):
      np.testing.assert_allclose(got, want, atol=1e-6)
    path = sl.viterbi(args, procedures, counters)
    best = int(np.argmax(sub_log_probs))
    np.testing.assert_array_equal(path.procedures, _annotation(sub_stacks[best], num_steps)[0])
    np.testing.assert_allclose(path.log_prob, sub_log_probs[best], atol=1e-6)
    samples = sample_many(args, procedures, counters)
    used = np.arange(num_steps)[:, None] < length
    for drawn, annotated in ((samples.procedures, procedures), (samples.counters, counters)):
      known = (annotated >= 0) & used
      assert (np.asarray(drawn)[:, known] == annotated[known]).all()
    # An impossible annotation (a counter out of range): −inf, zero marginals and zero gradients, no NaN.
    impossible = np.where(np.arange(num_steps)[:, None] == 1, [x.shape[2] for x in inputs.log_stop], -1)
    post, grads = posterior_and_grads(args, None, impossible)
    assert post.log_likelihood == -np.inf
    assert all((x == 0).all() for x in post.marginals + tuple(jax.tree.leaves(grads)))
    # Counters unknown (None): only procedures constrain the paths.
    log_z, _, _, _ = bf.stack_posterior(inputs, length, functools.partial(agrees, counters=np.full_like(counters, -1)))
    np.testing.assert_allclose(posterior_and_grads(args, procedures)[0].log_likelihood, log_z, atol=1e-6)


def _path_index(stacks, num_steps):
  return {np.stack(_annotation(stack, num_steps), -1).tobytes(): k for k, stack in enumerate(stacks)}


def test_sample_posterior_matches_enumeration():
  with jax.enable_x64(True):
    _, args, num_steps, _, (_, probs, stacks, log_probs) = _case((THREE, 4, 0.0), seed=5, scale=2.0)
    paths = sample_many(args)
  index = _path_index(stacks, num_steps)
  drawn = [index[np.stack([p, c], -1).tobytes()] for p, c in zip(np.asarray(paths.procedures),
                                                                  np.asarray(paths.counters))]
  np.testing.assert_allclose(paths.log_prob, log_probs[drawn], atol=1e-6)
  counts, n = collections.Counter(drawn), len(KEYS)
  for k, p in enumerate(probs):
    assert abs(counts[k] / n - p) <= 5 * np.sqrt(p * (1 - p) / n) + 2 / n, (k, counts[k] / n, p)


def test_two_levels_equal_the_lattice():
  """d = 2 with a root that always continues (and has room to) and may stop only after the last step is the
  two-level lattice: the root pushes with log_root whatever its counter."""
  num_steps, num_procs, capacity, length = 7, 3, 3, 6
  rng = np.random.default_rng(2)
  z = rng.normal(size=(num_steps, num_procs, capacity))
  lattice = (np.log(rng.dirichlet(np.ones(num_procs), num_steps)),
             np.log(rng.uniform(0.1, 1, (num_steps, num_procs, capacity))), -np.logaddexp(0, -z), -np.logaddexp(0, z))
  log_root, log_op, log_stop, log_cont = lattice
  root_stop = np.where(np.arange(num_steps)[:, None, None] == length - 1, 0.0, -np.inf) * np.ones((1, 1, num_steps))
  stack = sl.StackInputs((np.broadcast_to(log_root[:, None, None, :], (num_steps, 1, num_steps, num_procs)),), log_op,
                         (root_stop, log_stop), (np.zeros((num_steps, 1, num_steps)), log_cont), length)
  with jax.enable_x64(True):
    lattice = [jnp.asarray(x, jnp.float64) for x in lattice]
    args = _jnp(stack, jnp.float64)
    want, got = php_jax.forward_backward(*lattice, length=length), sl.forward_backward(args)
    want_path, got_path = php_jax.viterbi(*lattice, length=length), sl.viterbi(args)
  np.testing.assert_allclose(got.log_likelihood, want.log_likelihood, atol=1e-6)
  np.testing.assert_allclose(got.marginals[1], want.v, atol=1e-6)
  np.testing.assert_array_equal(got_path.procedures[:, 1], want_path.procedures)
  np.testing.assert_array_equal(got_path.counters[:, 1], want_path.counters)
  np.testing.assert_allclose(got_path.log_prob, want_path.log_prob, atol=1e-6)


def test_long_trace_float32_large_logits_is_finite():
  """T = 2,000, logits ×1e4, −inf masks on everything of procedure 1 (procedure 0 keeps a path possible)."""
  sizes, capacities, num_steps = (1, 2, 2), (16, 8, 16), 2000  # Π C = 2,048 ≥ T: the hierarchy can run that long
  rng = np.random.default_rng(0)
  inputs = random_stack(rng, sizes, capacities, num_steps, scale=1e4)

  def masked(x, level):  # frames of procedure 1 at level ≥ 1
    hit = (rng.uniform(size=x.shape) < 0.2) & (np.arange(x.shape[1]) == 1).reshape((1, -1) + (1,) * (x.ndim - 2))
    return np.where(hit & (level > 0), -np.inf, x)

  inputs = _jnp(sl.StackInputs(tuple(masked(x, i) for i, x in enumerate(inputs.log_call)), masked(inputs.log_act, 1),
                               tuple(masked(x, i) for i, x in enumerate(inputs.log_stop)), inputs.log_cont),
                jnp.float32)
  post, grads = posterior_and_grads(inputs)
  path = sl.viterbi(inputs)
  assert np.isfinite(post.log_likelihood) and post.log_likelihood < -1e4
  assert all(np.isfinite(x).all() for x in jax.tree.leaves((post, grads)))
  for marginal in post.marginals:
    np.testing.assert_allclose(marginal.sum(axis=(1, 2)), 1.0, atol=1e-3)
  np.testing.assert_allclose(grads.log_act, post.marginals[-1], atol=1e-5)
  assert np.isfinite(path.log_prob) and path.log_prob <= post.log_likelihood + 1e-6 * abs(post.log_likelihood)


def test_padding_is_a_no_op_and_batching_works():
  """Six steps padded to eight with garbage give the results of the six steps alone (for sampling, the
  enumeration tests pad with garbage too)."""
  with jax.enable_x64(True):
    (sizes, capacities, _), length = THREE, 6
    padded = _jnp(random_stack(np.random.default_rng(9), sizes, capacities, 8, mask_prob=0.1, length=length),
                  jnp.float64)
    truncated = sl.StackInputs(*jax.tree.map(lambda x: x[:length], tuple(padded[:4])), length=length)

    def same(got, want, pad):  # got[:length] = want; got = pad after
      got, want = np.asarray(got), np.asarray(want)
      np.testing.assert_allclose(got[:length], want, rtol=1e-9, atol=1e-9)
      np.testing.assert_array_equal(got[length:], pad)

    (got, got_grads), (want, want_grads) = posterior_and_grads(padded), posterior_and_grads(truncated)
    np.testing.assert_allclose(got.log_likelihood, want.log_likelihood, rtol=1e-9)
    for g, w in zip(got.marginals + tuple(jax.tree.leaves(got_grads)),
                    want.marginals + tuple(jax.tree.leaves(want_grads))):
      same(g, w, 0.0)
    got, want = sl.viterbi(padded), sl.viterbi(truncated)
    same(got.procedures, want.procedures, php_jax.NO_FRAME)
    same(got.counters, want.counters, php_jax.NO_FRAME)
    np.testing.assert_allclose(got.log_prob, want.log_prob, rtol=1e-9)

    # A batch of demonstrations of different lengths under jit(vmap(·)) equals the one-by-one results.
    batch = [_case((THREE, n, 0.0), seed=n)[1] for n in (6, 2, 5)]
    posts, paths = jax.jit(jax.vmap(lambda x: (sl.forward_backward(x), sl.viterbi(x))))(
        jax.tree.map(lambda *x: jnp.stack(x), *batch))
    for b, one in enumerate(batch):
      want = posterior_and_grads(one)[0]
      np.testing.assert_allclose(posts.log_likelihood[b], want.log_likelihood, rtol=1e-9)
      for got, marginal in zip(posts.marginals, want.marginals):
        np.testing.assert_allclose(got[b], marginal, atol=1e-9)
      np.testing.assert_array_equal(paths.procedures[b], sl.viterbi(one).procedures)


@pytest.mark.parametrize("case", [(THREE, 4, 0.15), (THREE, 1, 0.0), (FOUR, 3, 0.0)])
def test_top_k_matches_enumeration(case):
  """The k most likely stack trajectories in order; past the possible ones (a single step has six), −inf and
  NO_FRAME."""
  k = 8
  with jax.enable_x64(True):
    _, args, num_steps, depth, (_, _, stacks, log_probs) = _case(case, seed=7)
    best, path = sl.top_k(k, args), sl.viterbi(args)
  order = np.argsort(-log_probs, kind="stable")
  possible = min(k, int(np.isfinite(log_probs).sum()))
  assert best.procedures.shape == best.counters.shape == (k, num_steps, depth) and best.log_prob.shape == (k,)
  np.testing.assert_allclose(best.log_prob[:possible], log_probs[order[:possible]], atol=1e-6)
  for i in range(possible):
    want_procedures, want_counters = _annotation(stacks[order[i]], num_steps)
    np.testing.assert_array_equal(best.procedures[i], want_procedures)
    np.testing.assert_array_equal(best.counters[i], want_counters)
  assert np.isneginf(best.log_prob[possible:]).all() and (best.procedures[possible:] == php_jax.NO_FRAME).all()
  np.testing.assert_array_equal(best.procedures[0], path.procedures)
  assert (possible < k) == (case[1] == 1)


def test_where_no_path_explains_the_actions_entropy_kl_and_cross_entropy_are_0_with_finite_gradients():
  p = random_stack(np.random.default_rng(3), (1, 2, 2), (4, 3, 2), 4)
  q = random_stack(np.random.default_rng(4), (1, 2, 2), (4, 3, 2), 4)
  never = p._replace(log_act=np.full_like(p.log_act, -np.inf))  # no action can be taken: no path

  def measures(log_act):
    p_none = never._replace(log_act=log_act)
    return jnp.stack([sl.posterior_entropy(p_none), sl.kl_divergence(p_none, q), sl.cross_entropy(p_none, q),
                      sl.kl_divergence(p_none, p_none)])

  np.testing.assert_array_equal(measures(never.log_act), 0.0)
  assert np.all(np.isfinite(jax.jacrev(measures)(jnp.asarray(never.log_act))))


def test_where_no_path_explains_the_actions_viterbi_and_samples_give_no_frame_and_minus_inf():
  never = random_stack(np.random.default_rng(3), (1, 2, 2), (4, 3, 2), 4)
  never = never._replace(log_act=np.full_like(never.log_act, -np.inf))  # no action can be taken: no path
  for path in (sl.viterbi(never), sl.sample_posterior(jax.random.key(0), never)):
    assert np.isneginf(path.log_prob)
    assert np.all(np.asarray(path.procedures) == php_jax.NO_FRAME)
    assert np.all(np.asarray(path.counters) == php_jax.NO_FRAME)


def test_entropy_kl_and_cross_entropy_match_enumeration():
  """Against every trajectory's probability under p and q (three levels, padding, −inf masks), also restricted
  to an annotation (the agreeing trajectories only), and +inf where q rules out a trajectory p allows."""
  (shape, length, _) = case = (THREE, 4, 0.15)
  with jax.enable_x64(True):
    _, p, num_steps, depth, (log_z, _, stacks, log_probs) = _case(case, seed=2)
    q_numpy, q, _, _, _ = _case((shape, length, 0.0), seed=12)
    q_log_probs = bf.stack_posterior(q_numpy, length)[3]  # the same trajectories in the same order
    free = sl.posterior_entropy(p), sl.cross_entropy(p, q), sl.kl_divergence(p, q)
    # Restricted: level 1's procedure at step 1 is the most likely trajectory's.
    known = stacks[int(np.argmax(log_probs))][1][1][0]
    procedures = np.full((num_steps, depth), -1, np.int32)
    procedures[1, 1] = known
    p_known, q_known = php_jax.StackLattice(p, procedures), php_jax.StackLattice(q, procedures)
    unknown = php_jax.StackLattice(p, np.full_like(procedures, -1))
    restricted = jax.device_get((p_known.entropy(), p_known.cross_entropy(q_known), p_known.kl_divergence(q_known),
                                 unknown.kl_divergence(q_known)))
  want_entropy, want_cross = bf.entropy(log_probs, log_z), bf.cross_entropy(log_probs, q_log_probs)
  np.testing.assert_allclose(free, [want_entropy, want_cross, want_cross - want_entropy], atol=1e-6)
  agree = np.array([stack[1][1][0] == known for stack in stacks])
  assert want_cross > want_entropy and 1 < np.isfinite(log_probs[agree]).sum() < np.isfinite(log_probs).sum()
  sub, sub_q = log_probs[agree], q_log_probs[agree]
  want_entropy, want_cross = bf.entropy(sub, np.logaddexp.reduce(sub)), bf.cross_entropy(sub, sub_q)
  np.testing.assert_allclose(restricted[:3], [want_entropy, want_cross, want_cross - want_entropy], atol=1e-6)
  assert restricted[3] == np.inf


def test_tempered_samples_match_enumeration():
  """Frequencies of P(ζ | ξ)^(1/temperature), renormalised: the samples of the lattice divided by temperature,
  key for key; log_prob stays the untempered log P(ζ, ξ)."""
  temperature = 2.5
  with jax.enable_x64(True):
    _, args, num_steps, _, (_, _, stacks, log_probs) = _case((THREE, 4, 0.0), seed=5, scale=2.0)
    divided = sl.StackInputs(*jax.tree.map(lambda x: x / temperature, tuple(args[:4])), length=args.length)
    paths, want = sample_many(args, temperature=temperature), sample_many(divided)
  np.testing.assert_array_equal(paths.procedures, want.procedures)
  np.testing.assert_array_equal(paths.counters, want.counters)
  index = _path_index(stacks, num_steps)
  drawn = [index[np.stack([p, c], -1).tobytes()] for p, c in zip(paths.procedures, paths.counters)]
  np.testing.assert_allclose(paths.log_prob, log_probs[drawn], atol=1e-6)
  probs = np.exp(log_probs / temperature - np.logaddexp.reduce(log_probs / temperature))
  counts, n = collections.Counter(drawn), len(KEYS)
  for k, p in enumerate(probs):
    assert abs(counts[k] / n - p) <= 5 * np.sqrt(p * (1 - p) / n) + 2 / n, (k, counts[k] / n, p)


@pytest.mark.parametrize("temperature", [0.5, 3.0])
def test_tempered_log_likelihood_and_its_gradients_match_enumeration(temperature):
  """T · log Σ P(ζ, ξ)^(1/T), and its jax.grad the events' posteriors under P(ζ | ξ)^(1/T) renormalised; a
  fully annotated path keeps its log P(ζ, ξ)."""
  with jax.enable_x64(True):
    inputs, args, num_steps, depth, (_, _, stacks, log_probs) = _case((THREE, 4, 0.15), seed=7, scale=2.0)
    tempered = jax.jit(jax.value_and_grad(
        lambda fields: sl.log_likelihood(sl.StackInputs(*fields, length=args.length), temperature=temperature)))
    value, grads = jax.device_get(tempered(tuple(args[:4])))
    best = int(np.argmax(log_probs))
    path_value = sl.log_likelihood(args, *_annotation(stacks[best], num_steps), temperature=temperature)
  scaled = log_probs / temperature
  np.testing.assert_allclose(value, temperature * np.logaddexp.reduce(scaled), atol=1e-6)
  events = event_posteriors(inputs, inputs.length, np.exp(scaled - np.logaddexp.reduce(scaled)), stacks)
  np.testing.assert_allclose(grads[1], events["marginals"][-1], atol=1e-6)
  for i in range(depth - 1):
    np.testing.assert_allclose(grads[0][i], events["call"][i], atol=1e-6)
  for i in range(depth):
    np.testing.assert_allclose(grads[2][i], events["stop"][i], atol=1e-6)
    np.testing.assert_allclose(grads[3][i], events["cont"][i], atol=1e-6)
  np.testing.assert_allclose(path_value, log_probs[best], atol=1e-6)


def test_stack_lattice_structure_answers_every_query_and_passes_through_jit_and_vmap():
  with jax.enable_x64(True):
    _, args, _, _, (log_z, _, _, _) = _case((THREE, 4, 0.0), seed=4)
    _, other, _, _, (other_log_z, _, _, _) = _case((THREE, 3, 0.0), seed=6)
    lattice, key = php_jax.StackLattice(args), jax.random.key(1)
    post = sl.forward_backward(args)
    pairs = [(lattice.posterior(), post), (lattice.marginals(), post.marginals), (lattice.argmax(), sl.viterbi(args)),
             (lattice.top_k(8), sl.top_k(8, args)),
             (lattice.sample(key, 0.5), sl.sample_posterior(key, args, temperature=0.5)),
             (lattice.entropy(), sl.posterior_entropy(args))]
    lattices = jax.vmap(php_jax.StackLattice)(jax.tree.map(lambda *x: jnp.stack(x), args, other))
    log_partitions = jax.jit(jax.vmap(lambda s: s.log_partition()))(lattices)
  for got, want in pairs:
    for g, w in zip(jax.tree.leaves(got), jax.tree.leaves(want)):
      np.testing.assert_array_equal(g, w)
  assert isinstance(lattices, php_jax.StackLattice) and lattices.inputs.log_act.shape[0] == 2
  np.testing.assert_allclose(log_partitions, [log_z, other_log_z], atol=1e-9)


def _small_stack(length=None):
  (sizes, capacities, num_steps) = THREE
  return _jnp(random_stack(np.random.default_rng(0), sizes, capacities, num_steps, length=length), jnp.float32)


def _annotated(entry, value, name="procedures"):
  values = np.full((6, 3), -1, np.int32)
  values[entry] = value
  return {name: values}


@pytest.mark.parametrize("call, message", [
    (lambda x: sl.log_likelihood(x, np.zeros((6, 2), np.int32)), r"procedures must have shape \(6, 3\); got \(6, 2\)"),
    (lambda x: sl.forward_backward(x, counters=np.zeros((6, 3))), "counters must be an integer array"),
    (lambda x: sl.viterbi(x, **_annotated((2, 1), 3)), r"procedures\[2, 1\] = 3 is outside −1..K_1−1 = −1..1"),
    (lambda x: sl.top_k(2, x, **_annotated((0, 2), 2, "counters")),
     r"counters\[0, 2\] = 2 is outside −1..C_2−1 = −1..1"),
    (lambda x: sl.posterior_entropy(x, **_annotated((4, 0), -2, "counters")), r"counters\[4, 0\] = -2"),
    (lambda x: sl.forward_backward(x._replace(length=2.5)), r"length must be an integer in 1..T = 1..6; got 2.5"),
    (lambda x: sl.viterbi(x._replace(length=True)), r"length must be an integer in 1..T = 1..6; got True"),
    (lambda x: sl.log_likelihood(x._replace(length=np.array([2, 3]))), r"got an array of shape \(2,\)"),
    (lambda x: sl.log_likelihood(x._replace(length=7)), r"length must be in 1..T = 1..6; got 7"),
    (lambda x: sl.sample_posterior(jax.random.key(0), x, temperature=0.0), "temperature must be a finite number > 0"),
    (lambda x: sl.sample_posterior(jax.random.key(0), x, temperature=-1), "temperature must be a finite number > 0"),
    (lambda x: sl.sample_posterior(jax.random.key(0), x, temperature=np.inf), "temperature"),
    (lambda x: sl.sample_posterior(jax.random.key(0), x, temperature=True), "temperature"),
    (lambda x: sl.log_likelihood(x, temperature=0.0), "temperature must be a finite number > 0"),
    (lambda x: sl.top_k(0, x), "k must be an int ≥ 1; got 0"),
    (lambda x: sl.kl_divergence(x, x._replace(log_act=x.log_act[:, :1])), "q: log_act must have shape"),
    (lambda x: sl.cross_entropy(x._replace(length=3), x._replace(length=4)), "p and q must have the same length"),
    (lambda x: sl.kl_divergence(x, _jnp(random_stack(np.random.default_rng(0), *FOUR), jnp.float32)),
     "the same number of levels"),
    (lambda x: php_jax.StackLattice(x, counters=np.zeros((6, 2), np.int32)), r"counters must have shape \(6, 3\)"),
    (lambda x: php_jax.StackLattice(x).kl_divergence(x), "other must be a StackLattice; got a StackInputs"),
])
def test_refusals_name_the_argument(call, message):
  with pytest.raises(ValueError, match=message):
    call(_small_stack())


def test_what_is_not_refused():
  """Annotation values on padding are ignored; traced ones out of range match nothing (under jit only shapes
  and dtypes are checked); arrays of different dtypes are computed in the promoted one. And one dialect: a
  path is an annotation, the whole path gives its complete-data likelihood."""
  with jax.enable_x64(True):
    inputs = _case((THREE, 4, 0.0), seed=3)[1]
    unknown, padded = np.full((6, 3), -1, np.int32), np.full((6, 3), -1, np.int32)
    padded[4:] = 9
    free, with_padding = sl.log_likelihood(inputs, unknown), sl.log_likelihood(inputs, padded)
    traced = jax.jit(sl.log_likelihood)(inputs, _annotated((2, 1), 3)["procedures"])
    mixed = sl.log_likelihood(inputs._replace(log_act=inputs.log_act.astype(jnp.float32)), unknown)
    rounded = sl.log_likelihood(inputs._replace(log_act=inputs.log_act.astype(jnp.float32).astype(jnp.float64)),
                                unknown)
    path = sl.viterbi(inputs)
    complete = sl.log_likelihood(inputs, path.procedures, path.counters)
  np.testing.assert_array_equal(with_padding, free)
  assert np.isneginf(traced)
  np.testing.assert_array_equal(mixed, rounded)
  np.testing.assert_allclose(complete, path.log_prob, atol=1e-9)
