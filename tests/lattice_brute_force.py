"""Reference E-step by enumerating every latent path, in float64 numpy, independent of php_jax.lattice."""
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
