"""The networks a configuration describes: a fresh hierarchy, and the root network that stands in for the
untrained levels above a level trained level-wise."""
from __future__ import annotations

from flax import nnx

from php_jax import encoders
from php_jax.hierarchy import HierarchySpec
from php_jax.model import PHPHierarchy, RootLSTM, RootMLP
from php_jax.training.config import TrainConfig


def make_hierarchy(spec: HierarchySpec, config: TrainConfig, graph: tuple | None = None) -> PHPHierarchy:
  """A freshly initialised hierarchy; graph: its call graph (`call_graph`), None: every call allowed."""
  return PHPHierarchy(spec, hidden=config.hidden, tau_in_termination=config.tau_in_termination,
                      tau_limit=config.tau_limit, allowed_ops=graph, trunk=config.trunk,
                      memory=encoders.DEFAULT_WIDTH if config.memory == "gru" else None,
                      end_given=config.episode_end == "environment",
                      rngs=nnx.Rngs(config.network_seed))


def make_root(spec: HierarchySpec, level: int, config: TrainConfig) -> nnx.Module | None:
  """The root network standing in for the untrained levels above `level` (None for the root level)."""
  if level == 0:
    return None
  rngs = nnx.Rngs(config.network_seed + 1000 + level)
  if config.root == "lstm":
    return RootLSTM(spec.obs_dim, spec.num_procs(level), config.root_hidden, rngs=rngs)
  return RootMLP(spec.obs_dim, spec.num_procs(level), (config.root_hidden,), rngs=rngs)
