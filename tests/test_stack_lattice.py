"""Whole-stack E-step against brute-force enumeration of stack trajectories, the two-level lattice, the EG
identities, annotation, decoding, sampling, padding, batching and long-trace numerics."""
import collections
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import php_jax
from php_jax import stack_lattice as sl

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


def enumerate_paths(inputs, length):
  """Every stack trajectory of `length` steps, following the executor's semantics step by step.

  Returns a list of (stacks, log_prob): stacks[t] is the tuple of (h_i, τ_i) for levels 0..d-1 at step t.
  """
  log_call, log_act, log_stop, log_cont = (inputs.log_call, np.asarray(inputs.log_act), inputs.log_stop,
                                           inputs.log_cont)
  depth = len(log_stop)
  sizes = [x.shape[1] for x in log_stop]
  capacities = [x.shape[2] for x in log_stop]
  paths = []

  def push(t, frames, log_prob):
    """Completes frames (levels 0..j) down to level d-1 with fresh frames: yields (frames, log_prob)."""
    if len(frames) == depth:
      yield frames, log_prob
      return
    level = len(frames) - 1
    h, tau = frames[-1]
    for callee in range(sizes[level + 1]):
      yield from push(t, frames + [(callee, 0)], log_prob + log_call[level][t, h, tau, callee])

  def walk(t, frames, stacks, log_prob):
    stacks = stacks + [tuple(frames)]
    log_prob += log_act[(t,) + frames[-1]]
    if t == length - 1:
      paths.append((stacks, log_prob + sum(log_stop[i][(t,) + frames[i]] for i in range(depth))))
      return
    stopped = 0.0
    for j in reversed(range(depth)):  # j: the first level from the bottom that continues
      h, tau = frames[j]
      if tau + 1 < capacities[j]:
        resumed = log_prob + stopped + log_cont[j][t, h, tau]
        for new_frames, new_log_prob in push(t + 1, frames[:j] + [(h, tau + 1)], resumed):
          walk(t + 1, new_frames, stacks, new_log_prob)
      stopped += log_stop[j][t, h, tau]

  for frames, log_prob in push(0, [(0, 0)], 0.0):
    walk(0, frames, [], log_prob)
  return paths


def _logsumexp(x):
  x = np.asarray(x, float)
  peak = x.max()
  return peak + np.log(np.exp(x - peak).sum()) if np.isfinite(peak) else -np.inf


def posterior(inputs, length, agrees=lambda stacks: True):
  """Brute force over the paths that agree: (log_likelihood, probabilities [P], stacks list, log_probs)."""
  paths = [(s, lp) for s, lp in enumerate_paths(inputs, length) if agrees(s)]
  log_probs = np.array([lp for _, lp in paths])
  log_z = _logsumexp(log_probs)
  probs = np.exp(log_probs - log_z) if np.isfinite(log_z) else np.zeros_like(log_probs)
  return log_z, probs, [s for s, _ in paths], log_probs


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
_sample_many = jax.jit(jax.vmap(sl.sample_posterior, (0, None, None, None)))


def sample_many(inputs, procedures=None, counters=None):
  """sample_posterior for each of KEYS, compiled once per shape like posterior_and_grads; numpy out."""
  unknown = np.full((inputs.log_act.shape[0], len(inputs.log_stop)), -1, np.int32)
  return jax.device_get(_sample_many(KEYS, inputs, unknown if procedures is None else procedures,
                                     unknown if counters is None else counters))


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
  (inputs as float64 numpy, the same as jax arrays, T, d, posterior(inputs, length))."""
  (sizes, capacities, num_steps), length, mask_prob = case
  while True:
    inputs = random_stack(np.random.default_rng(seed), sizes, capacities, num_steps, scale, mask_prob, length)
    enumerated = posterior(inputs, length)
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

    log_z, sub_probs, sub_stacks, sub_log_probs = posterior(inputs, length, agrees)
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
    log_z, _, _, _ = posterior(inputs, length, functools.partial(agrees, counters=np.full_like(counters, -1)))
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
  np.testing.assert_array_equal(got_path.procedures[:, 1], want_path.procedure)
  np.testing.assert_array_equal(got_path.counters[:, 1], want_path.counter)
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
