"""Reference E-step by enumerating every latent path, of the two-level lattice and of the whole call stack, in
float64 numpy, independent of php_jax.inference.lattice and php_jax.inference.stack_lattice."""
import numpy as np


def random_lattice(rng, num_steps, num_procs, capacity, scale=1.0, mask_prob=0.0):
  """Random normalised log-probabilities (log_root, log_op, log_stop, log_cont), optionally −inf-masked."""
  def log_softmax(x, axis):
    x = x - x.max(axis=axis, keepdims=True)
    return x - np.log(np.exp(x).sum(axis=axis, keepdims=True))

  log_root = log_softmax(scale * rng.normal(size=(num_steps, num_procs)), axis=1)
  log_op = np.log(rng.uniform(0.05, 1.0, size=(num_steps, num_procs, capacity))) * scale
  z = scale * rng.normal(size=(num_steps, num_procs, capacity))
  log_stop, log_cont = -np.logaddexp(0, -z), -np.logaddexp(0, z)
  if mask_prob:
    log_op = np.where(rng.uniform(size=log_op.shape) < mask_prob, -np.inf, log_op)
    log_stop = np.where(rng.uniform(size=log_stop.shape) < mask_prob, -np.inf, log_stop)
  return log_root, log_op, log_stop, log_cont


def path_log_prob(inputs, path):
  """log P(ζ, ξ) of path = [(h_0, τ_0), ..., (h_{L-1}, τ_{L-1})] straight from the model's definition."""
  log_root, log_op, log_stop, log_cont = inputs
  (h0, tau0) = path[0]
  if tau0 != 0:
    return -np.inf
  total = log_root[0, h0]
  for t, (h, tau) in enumerate(path):
    total += log_op[t, h, tau]
    if t == len(path) - 1:
      total += log_stop[t, h, tau]
    else:
      h_next, tau_next = path[t + 1]
      if tau_next == 0:
        total += log_stop[t, h, tau] + log_root[t + 1, h_next]
      elif h_next == h and tau_next == tau + 1:
        total += log_cont[t, h, tau]
      else:
        return -np.inf
  return total


def all_paths(num_procs, capacity, length):
  """Every structurally valid path of the given length."""
  paths = [[(h, 0)] for h in range(num_procs)]
  for _ in range(length - 1):
    grown = []
    for path in paths:
      h, tau = path[-1]
      grown += [path + [(h2, 0)] for h2 in range(num_procs)]
      if tau + 1 < capacity:
        grown.append(path + [(h, tau + 1)])
    paths = grown
  return paths


def enumerate_posterior(inputs, length):
  """Brute force: (log_likelihood, v [T,K,C], w [T,K,C], paths, log_probs)."""
  num_steps, num_procs, capacity = inputs[1].shape
  paths = all_paths(num_procs, capacity, length)
  log_probs = np.array([path_log_prob(inputs, p) for p in paths])
  log_z = np.logaddexp.reduce(log_probs) if np.isfinite(log_probs).any() else -np.inf
  post = np.exp(log_probs - log_z) if np.isfinite(log_z) else np.zeros_like(log_probs)
  v = np.zeros((num_steps, num_procs, capacity))
  w = np.zeros_like(v)
  for p, path in zip(post, paths):
    for t, (h, tau) in enumerate(path):
      v[t, h, tau] += p
      if t + 1 < length and path[t + 1][1] == tau + 1:
        w[t, h, tau] += p
  return log_z, v, w, paths, log_probs


def entropy(log_probs, log_z):
  p = np.exp(log_probs - log_z)
  nz = p > 0
  return float(-(p[nz] * (log_probs[nz] - log_z)).sum())


def cross_entropy(log_probs_p, log_probs_q):
  """H(p, q) = −Σ_ζ p(ζ | ξ) log q(ζ | ξ) from every path's log P(ζ, ξ) under p and q, in the same order:
  +inf where q rules out a path p allows."""
  p = np.exp(log_probs_p - np.logaddexp.reduce(log_probs_p))
  with np.errstate(invalid="ignore"):
    log_q = log_probs_q - np.logaddexp.reduce(log_probs_q)
  nz = p > 0
  return float(-(p[nz] * log_q[nz]).sum())


def prefix_log_prob(inputs, path):
  """log-probability of a path prefix (h_0, τ_0) .. (h_t, τ_t) emitting a_0 .. a_t: path_log_prob without
  the last step's termination factor, which is not decided yet."""
  log_root, log_op, log_stop, log_cont = inputs
  (h, tau), t = path[-1], len(path) - 1
  undecided = log_stop.copy()
  undecided[t, h, tau] = 0.0
  return path_log_prob((log_root, log_op, undecided, log_cont), path)


def path_features(paths, shape, length):
  """Per path, how often each input's entry enters log P(ζ, ξ): four count arrays (root [P, T, K], op, stop,
  cont [P, T, K, C]), so that log P(ζ, ξ) = Σ counts · inputs. Lets JAX differentiate the enumeration."""
  num_steps, num_procs, capacity = shape
  root = np.zeros((len(paths), num_steps, num_procs))
  op, stop, cont = (np.zeros((len(paths),) + tuple(shape)) for _ in range(3))
  for i, path in enumerate(paths):
    root[i, 0, path[0][0]] = 1
    for t, (h, tau) in enumerate(path):
      op[i, t, h, tau] = 1
      if t == length - 1 or path[t + 1][1] == 0:
        stop[i, t, h, tau] = 1
        if t < length - 1:
          root[i, t + 1, path[t + 1][0]] = 1
      else:
        cont[i, t, h, tau] = 1
  return root, op, stop, cont


def stack_paths(inputs, length):
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


def stack_posterior(inputs, length, agrees=lambda stacks: True):
  """Brute force over the paths that agree: (log_likelihood, probabilities [P], stacks list, log_probs)."""
  paths = [(s, lp) for s, lp in stack_paths(inputs, length) if agrees(s)]
  log_probs = np.array([lp for _, lp in paths])
  log_z = _logsumexp(log_probs)
  probs = np.exp(log_probs - log_z) if np.isfinite(log_z) else np.zeros_like(log_probs)
  return log_z, probs, [s for s, _ in paths], log_probs
