"""PHP networks in Flax NNX (paper §4.1.2): per procedure an operation MLP and a termination MLP over the
observation (or its encoding shared by the level, and the level's memory of the episode: `encoders`)
concatenated with τ as a real number; root networks (MLP or LSTM) standing in for untrained
levels above; a whole hierarchy of PHP levels that the executor runs as a Policy.
"""
from __future__ import annotations

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from flax import nnx

from php_jax import encoders
from php_jax.hierarchy import HierarchySpec, check_observes, check_size


def _check_sizes(name: str, sizes, least: int = 1) -> tuple[int, ...]:
  """sizes (a sequence of ints, each ≥ least) as a tuple; refuses anything else naming it."""
  if not isinstance(sizes, (tuple, list)):
    raise ValueError(f"{name} must be a tuple of integers; got {sizes!r}")
  return tuple(check_size(f"{name}[{i}]", n, least) for i, n in enumerate(sizes))


_he_init = nnx.initializers.variance_scaling(2.0, "fan_in", "normal", in_axis=-2, out_axis=-1,
                                             batch_axis=(0,))


class ProcedureMLPs(nnx.Module):
  """K independent ReLU MLPs over concat(obs, τ), evaluated for every procedure at once.

  The first layer is split into an observation part, computed once per observation, and a τ part added per
  counter, so a [N observations × M counters] grid costs N + M first-layer products, not N × M. Activations
  are laid out [K, N·M, H] and the output [K, out_dim, N, M]: plain batched matmuls, and per-output slabs
  that the heads reduce over without touching a short minor axis (on the CPU, for 160 views at a lowest level
  with hidden (32,), this cut a training gradient from 123 to 103 ms; BUILD.md).
  """

  def __init__(self, num_procs: int, obs_dim: int, hidden: tuple[int, ...], out_dim: int, *,
               observes: tuple[tuple[bool, ...], ...] | None = None, rngs: nnx.Rngs):
    """observes: [K][obs_dim] bools, which observation entries each procedure's MLP sees (the others get no
    weight); None: every entry."""
    sizes = (obs_dim + 1, *hidden, out_dim)
    kernels = [_he_init(rngs.params(), (num_procs, n_in, n_out)) for n_in, n_out in zip(sizes[:-1], sizes[1:])]
    if observes is not None:  # what a procedure does not observe gets no weight (and, masked, no gradient)
      seen = jnp.concatenate([jnp.asarray(observes, bool), jnp.ones((num_procs, 1), bool)], axis=1)
      kernels[0] = jnp.where(seen[:, :, None], kernels[0], 0.0)
    self.kernels = nnx.List([nnx.Param(kernel) for kernel in kernels])
    self.biases = nnx.List([nnx.Param(jnp.zeros((num_procs, n_out))) for n_out in sizes[1:]])
    self.observes = observes

  def __call__(self, obs: jax.Array, tau: jax.Array) -> jax.Array:
    """obs: [N, obs_dim]; tau: [M] float → [K, out_dim, N, M]."""
    first = self.kernels[0][...]
    num_procs, num_obs, num_taus = first.shape[0], obs.shape[0], tau.shape[0]
    from_obs_kernel = first[:, :-1]
    if self.observes is not None:
      from_obs_kernel = jnp.where(np.asarray(self.observes)[:, :, None], from_obs_kernel, 0.0)
    from_obs = jnp.einsum("nd,kdh->knh", obs, from_obs_kernel)
    from_tau = tau[None, :, None] * first[:, -1][:, None, :] + self.biases[0][...][:, None, :]  # [K, M, H]
    x = (from_obs[:, :, None, :] + from_tau[:, None, :, :]).reshape(num_procs, num_obs * num_taus, -1)
    batched = ((0,), (0,))
    for kernel, bias in zip(list(self.kernels)[1:-1], list(self.biases)[1:-1]):
      x = jax.lax.dot_general(jax.nn.relu(x), kernel[...], (((2,), (1,)), batched)) + bias[...][:, None]
    if len(self.kernels) == 1:
      out = jnp.swapaxes(x, 1, 2)
    else:
      out = (jax.lax.dot_general(self.kernels[-1][...], jax.nn.relu(x), (((1,), (2,)), batched))
             + self.biases[-1][...][:, :, None])
    return out.reshape(num_procs, -1, num_obs, num_taus)


class PHPLevel(nnx.Module):
  """The K procedures of one level: operation η_h^τ(·|o) and termination ψ_h^τ(·|o) networks.

  The networks read the level's features of each step (`features`): the observation itself, or with a
  trunk its shared encoding (`encoders.Encoder`), computed once for the level's K procedures and their
  counters rather than once per procedure; with a history, beside it the history's state after the step.

  Attributes:
    op_sizes: factor sizes of the operation (callees of the next level, or the elementary action factors).
    tau_in_termination: whether ψ sees τ (the paper's per-level hyper-parameter); if not, τ is fed as 0.
    tau_limit: both networks see min(τ, tau_limit) (None: τ itself). A procedure whose decisions need only
      the first few counter values then behaves the same for any number of operations: a limit of 1 tells
      the first operation from the others, 0 hides τ.
    allowed_ops: `[K][Σ op_sizes]` bools: per procedure, which value of each operation factor it may take
      (which callee, or which value of each elementary action factor; the others get probability 0); None:
      any.
    observes: per procedure, None or the observation entries (indices) both its networks see
      (`HierarchySpec.observes`); None: every entry for every procedure.
    trunk: the width of the level's shared encoding (`encoders.Encoder`); None: the networks read the
      observation.
    fields: what the observation's numbers are (`encoders`), for the encoder; None: numbers.
    history: the level's memory of what was observed (`encoders.History`, reading the level's encoding), whose
      state every network reads beside the encoding; None: none.
    end_given: a demonstration's end is the environment's, not a return of the level's frames: the lattice
      takes their stop after the last action as given (probability 1) instead of learning it.
  Raises ValueError naming the argument: num_procs < 1, obs_dim < 0, no op_sizes or one < 1, a hidden size
  < 1, tau_limit < 0, allowed_ops of another shape, observes not one entry per procedure or naming an
  entry outside 0..obs_dim−1, a trunk < 1 or beside observes (a shared encoding sees every entry), fields
  without a trunk or of another size than obs_dim.
  """

  def __init__(self, num_procs: int, obs_dim: int, op_sizes: tuple[int, ...], hidden=(64, 64),
               tau_in_termination: bool = True, tau_limit: int | None = None,
               allowed_ops: tuple[tuple[bool, ...], ...] | None = None,
               observes: tuple[tuple[int, ...] | None, ...] | None = None, trunk: int | None = None,
               fields: tuple[encoders.Field, ...] | None = None, history: encoders.History | None = None,
               end_given: bool = False, *, rngs: nnx.Rngs):
    check_size("num_procs", num_procs)
    check_size("obs_dim", obs_dim, 0)
    if not _check_sizes("op_sizes", op_sizes):
      raise ValueError("op_sizes must name at least one operation factor; got ()")
    _check_sizes("hidden", hidden)
    if tau_limit is not None:
      check_size("tau_limit", tau_limit, 0)
    self.op_sizes = tuple(op_sizes)
    self.tau_in_termination = tau_in_termination
    self.tau_limit = tau_limit
    if allowed_ops is not None and np.shape(allowed_ops) != (num_procs, sum(self.op_sizes)):
      raise ValueError(f"allowed_ops must be [{num_procs}][{sum(self.op_sizes)}] (procedure, operation factor "
                       f"value); got shape {np.shape(allowed_ops)}")
    self.allowed_ops = None if allowed_ops is None else tuple(tuple(bool(c) for c in row) for row in allowed_ops)
    if observes is not None:
      if not (isinstance(observes, tuple) and len(observes) == num_procs):
        raise ValueError(f"observes must give one entry per procedure ({num_procs}), a tuple; got {observes!r}")
      check_observes((observes,), (tuple(f"procedure {k}" for k in range(num_procs)),), obs_dim)
    self.observes = observes
    if trunk is not None:
      check_size("trunk", trunk)
      if observes is not None:
        raise ValueError("trunk: a level whose procedures observe different entries (observes) cannot share "
                         "an encoding of the observation; give one or the other")
    if fields is not None and (trunk is None or encoders.size(fields) != obs_dim):
      raise ValueError(f"fields need a trunk (the encoder that reads them) and must take obs_dim = {obs_dim} "
                       f"numbers; got trunk {trunk}, fields of {encoders.size(fields)}")
    mask = None if observes is None else tuple(
        tuple(entries is None or d in entries for d in range(obs_dim)) for entries in observes)
    self.trunk = None if trunk is None else encoders.Encoder(fields or (encoders.Real(obs_dim),), trunk, rngs=rngs)
    self.history = history
    self.end_given = end_given
    features = (obs_dim if trunk is None else trunk) + (0 if history is None else history.width)
    self.operation = ProcedureMLPs(num_procs, features, tuple(hidden), sum(op_sizes), observes=mask, rngs=rngs)
    self.termination = ProcedureMLPs(num_procs, features, tuple(hidden), 1, observes=mask, rngs=rngs)

  def stop_log_probs(self, features: jax.Array, tau: jax.Array, length: jax.Array) -> tuple[jax.Array, jax.Array]:
    """(log ψ(1), log ψ(0)) [T, K, M] after each of a demonstration's T operations, from the features after
    them [T, ·]; with end_given, the stop after the last (length − 1) is certain."""
    z = self.termination_logits(features, tau)
    log_stop, log_cont = jax.nn.log_sigmoid(z), jax.nn.log_sigmoid(-z)
    if self.end_given:  # (after the last operation every frame stops: the lattice never continues there)
      log_stop = jnp.where((jnp.arange(z.shape[0]) == length - 1)[:, None, None], 0.0, log_stop)
    return log_stop, log_cont

  def encode(self, obs: jax.Array) -> jax.Array:
    """The level's encoding of observations [N, obs_dim]: [N, obs_dim] (no trunk) or [N, trunk]. Without a
    history these are the features every other method takes."""
    obs = jnp.asarray(obs, jnp.float32)  # a file's observations may be held narrower (`demos.compact_dtype`)
    return obs if self.trunk is None else self.trunk(obs)

  def features(self, observations: jax.Array, actions: jax.Array) -> jax.Array:
    """The features of a demonstration's steps, which every other method takes: observations [T+1, obs_dim],
    actions [T, F] → [T+1, ·], the encoding and, with a history, its state after each step."""
    encoded = self.encode(observations)
    if self.history is None:
      return encoded
    return jnp.concatenate([encoded, self.history(encoded, actions)], axis=1)

  def step_features(self, obs: jax.Array, state: jax.Array | None) -> jax.Array:
    """The features of one observation [obs_dim] → [1, ·], with the history's state after it where the
    level has one."""
    encoded = self.encode(obs[None])
    if self.history is None:
      return encoded
    if state is None:
      raise ValueError("a level with a history reads observations with its state: act through "
                       "PHPHierarchy.recall(memory)")
    return jnp.concatenate([encoded, state[None]], axis=1)

  def op_log_probs(self, obs: jax.Array, tau: jax.Array) -> list[jax.Array]:
    """Per factor f: [N, K, M, op_sizes[f]] log-probabilities (the factorized action head). obs: features
    [N, ·] (`features`)."""
    logits = jnp.transpose(self._operation_logits(obs, tau), (2, 0, 3, 1))
    splits = np.cumsum(self.op_sizes)[:-1]
    return [jax.nn.log_softmax(part, axis=-1) for part in jnp.split(logits, splits, axis=-1)]

  def log_op(self, obs: jax.Array, tau: jax.Array, ops: jax.Array) -> jax.Array:
    """log η_h^τ(ops_n | obs_n) for every procedure and counter. obs [N, ·] features (`features`), tau [M], ops
    [N, F] → [N, K, M]."""
    logits = self._operation_logits(obs, tau)                             # [K, Σ op_sizes, N, M]
    total, start = 0.0, 0
    for f, size in enumerate(self.op_sizes):
      part = logits[:, start:start + size]
      # The chosen logit by a one-hot select: unlike a gather, its gradient is not a scatter.
      chosen = jnp.sum(jnp.where(jax.nn.one_hot(ops[:, f], size, dtype=bool).T[None, :, :, None], part, 0.0),
                       axis=1)
      total, start = total + chosen - jax.nn.logsumexp(part, axis=1), start + size
    return jnp.transpose(total, (1, 0, 2))

  def termination_logits(self, obs: jax.Array, tau: jax.Array) -> jax.Array:
    """logit of ψ_h^τ(1 | obs). obs [N, ·] features (`features`), tau [M] → [N, K, M]; log ψ(1) = log σ(z),
    log ψ(0) = log σ(−z)."""
    tau = self._limited(tau) if self.tau_in_termination else jnp.zeros_like(tau)
    return jnp.transpose(self.termination(obs, tau)[:, 0], (1, 0, 2))

  def _operation_logits(self, obs: jax.Array, tau: jax.Array) -> jax.Array:
    """[K, Σ op_sizes, N, M] operation logits, −inf for the operations a procedure may not take."""
    logits = self.operation(obs, self._limited(tau))
    if self.allowed_ops is None:
      return logits
    return jnp.where(np.asarray(self.allowed_ops)[:, :, None, None], logits, -jnp.inf)

  def _limited(self, tau: jax.Array) -> jax.Array:
    return tau if self.tau_limit is None else jnp.minimum(tau, self.tau_limit)


class RootMLP(nnx.Module):
  """η_⊥(h | o_t): a ReLU MLP over each observation. [T, obs_dim] → [T, K] log-probabilities."""

  def __init__(self, obs_dim: int, num_children: int, hidden=(64, 64), *, rngs: nnx.Rngs):
    check_size("obs_dim", obs_dim, 0)
    check_size("num_children", num_children)
    _check_sizes("hidden", hidden)
    sizes = (obs_dim, *hidden)
    self.layers = nnx.List([nnx.Linear(a, b, rngs=rngs) for a, b in zip(sizes[:-1], sizes[1:])])
    self.head = nnx.Linear(sizes[-1], num_children, rngs=rngs)

  def __call__(self, observations: jax.Array) -> jax.Array:
    x = jnp.asarray(observations, jnp.float32)
    for layer in self.layers:
      x = jax.nn.relu(layer(x))
    return jax.nn.log_softmax(self.head(x), axis=-1)


class RootLSTM(nnx.Module):
  """η_⊥^LSTM(h | o_0..o_t): an LSTM over the observation sequence. [T, obs_dim] → [T, K] log-probabilities."""

  def __init__(self, obs_dim: int, num_children: int, hidden: int = 64, *, rngs: nnx.Rngs):
    check_size("obs_dim", obs_dim, 0)
    check_size("num_children", num_children)
    check_size("hidden", hidden)
    self.hidden = hidden
    self.cell = nnx.LSTMCell(obs_dim, hidden, rngs=rngs)
    self.head = nnx.Linear(hidden, num_children, rngs=rngs)

  def __call__(self, observations: jax.Array) -> jax.Array:
    zeros = jnp.zeros(self.hidden, jnp.float32)
    _, hidden = jax.lax.scan(lambda carry, obs: self.cell(carry, obs), (zeros, zeros),
                             jnp.asarray(observations, jnp.float32))
    return jax.nn.log_softmax(self.head(hidden), axis=-1)


class PHPHierarchy(nnx.Module):
  """A whole hierarchy of PHP levels; a Policy for the executor (argmax, or sampling when `sample`)."""

  def __init__(self, spec: HierarchySpec, hidden=(64, 64), tau_in_termination=None, sample: bool = False,
               tau_limit=None, allowed_ops=None, trunk: int | None = None, memory: int | None = None,
               end_given: bool = False, *, rngs: nnx.Rngs):
    """tau_in_termination, tau_limit, allowed_ops: per level, root first (PHPLevel); None: τ everywhere,
    unlimited, every operation allowed. Each procedure's networks see the observation entries spec.observes
    gives it (every entry where it gives none); trunk: each level's shared encoding width (PHPLevel), which
    reads spec.observation's fields where it gives them; None: none, or where those fields are structured
    (`encoders.structured`: categories, images, words) encoders.DEFAULT_WIDTH wide; memory: the width of
    each level's history of what was observed (`encoders.History`), None: none. With a memory the executor
    carries its state (`initial_memory`, `remember`) and asks the hierarchy bound to it (`recall`); end_given:
    its demonstrations end where their environment ended them, so the return after the last action is given,
    not learned (PHPLevel), and a replayed demonstration need not end with the root returning (`replay`)."""
    if not isinstance(spec, HierarchySpec):
      raise ValueError(f"spec must be a HierarchySpec; got {spec!r}")
    tau_in_termination = tau_in_termination or (True,) * spec.num_levels
    tau_limit = tau_limit or (None,) * spec.num_levels
    allowed_ops = allowed_ops or (None,) * spec.num_levels
    for name, values in (("tau_in_termination", tau_in_termination), ("tau_limit", tau_limit),
                         ("allowed_ops", allowed_ops)):
      if len(values) != spec.num_levels:
        raise ValueError(f"{name} needs one value per level ({spec.num_levels}); got {values}")
    self.spec = spec
    self.sample = sample
    observes = spec.observes or (None,) * spec.num_levels
    if trunk is None and encoders.structured(spec.observation):
      trunk = encoders.DEFAULT_WIDTH
    if memory is not None:
      check_size("memory", memory)

    def history():
      return None if memory is None else encoders.History(trunk or spec.obs_dim, spec.action_sizes, memory, rngs=rngs)

    self.levels = nnx.List([
        PHPLevel(spec.num_procs(i), spec.obs_dim, spec.op_sizes(i), hidden, tau_in_termination[i], tau_limit[i],
                 allowed_ops[i], observes[i], trunk, spec.observation if trunk else None, history(), end_given,
                 rngs=rngs)
        for i in range(spec.num_levels)])

  @property
  def memory(self) -> int | None:
    """The width of each level's history (`encoders.History`); None without a memory."""
    history = self.levels[0].history
    return None if history is None else history.width

  @property
  def end_given(self) -> bool:
    """Whether its demonstrations' ends are their environment's (PHPLevel.end_given, the same at every level)."""
    return self.levels[0].end_given

  def initial_memory(self) -> tuple:
    """The memory before an episode's first observation: per level its history's state ([memory] zeros);
    () without a memory."""
    return () if self.memory is None else tuple(level.history.initial() for level in self.levels)

  def remember(self, memory: tuple, obs: jax.Array, previous: jax.Array) -> tuple:
    """The memory after observing obs [obs_dim], reached by the action previous [F] (−1 at the start)."""
    if self.memory is None:
      return memory
    return tuple(level.history.step(state, level.encode(obs[None])[0], previous)
                 for level, state in zip(self.levels, memory))

  def recall(self, memory: tuple) -> "Recalled":
    """The hierarchy's statements (a Policy) as they read obs with this memory (`remember`'s)."""
    return Recalled(self, memory)

  def operation(self, level, proc, tau, obs, key, memory: tuple = ()):
    tau = jnp.asarray(tau, jnp.float32)[None]
    php = self.levels[level]
    factors = [lp[0, proc, 0] for lp in php.op_log_probs(php.step_features(obs, _state(memory, level)), tau)]
    if self.sample:
      keys = jax.random.split(key, len(factors))
      return jnp.stack([jax.random.categorical(k, lp) for k, lp in zip(keys, factors)]).astype(jnp.int32)
    return jnp.stack([jnp.argmax(lp) for lp in factors]).astype(jnp.int32)

  def terminates(self, level, proc, tau, obs, key, memory: tuple = ()):
    php = self.levels[level]
    features = php.step_features(obs, _state(memory, level))
    logit = php.termination_logits(features, jnp.asarray(tau, jnp.float32)[None])[0, proc, 0]
    if self.sample:
      return jax.random.bernoulli(key, jax.nn.sigmoid(logit))
    return logit > 0


def _state(memory: tuple, level: int) -> jax.Array | None:
  return memory[level] if memory else None


class Recalled(NamedTuple):
  """A hierarchy with a memory, bound to the memory of one moment: the Policy the executor asks."""
  hierarchy: PHPHierarchy
  memory: tuple

  def operation(self, level, proc, tau, obs, key):
    return self.hierarchy.operation(level, proc, tau, obs, key, self.memory)

  def terminates(self, level, proc, tau, obs, key):
    return self.hierarchy.terminates(level, proc, tau, obs, key, self.memory)
