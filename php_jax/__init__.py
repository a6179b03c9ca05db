"""php_jax: Parametrized Hierarchical Procedures (Fox et al., ICLR 2018) in JAX."""
__version__ = "0.1.0"  # the one place the version is set (pyproject.toml reads it)

from php_jax.inference.lattice import (NO_FRAME, LatticeInputs, LatticePath, LatticePosterior, annotate,
                                       complete_log_likelihood, forward_backward, max_marginal_path,
                                       posterior_entropy, sample_posterior, top_level, validate_inputs, viterbi)
from php_jax.inference.lattice_ops import (LatticeFilter, TwoLevelLattice, cross_entropy, differentiable_sample,
                                           forward_filter, kl_divergence, top_k)
# The stack's functions share the two-level ones' names: php_jax.inference.stack_lattice.*, or php_jax.StackLattice.
from php_jax.inference.stack_lattice import StackInputs, StackLattice, StackPath, StackPosterior

__all__ = ["NO_FRAME", "LatticeFilter", "LatticeInputs", "LatticePath", "LatticePosterior", "StackInputs",
           "StackLattice", "StackPath", "StackPosterior", "TwoLevelLattice", "annotate", "complete_log_likelihood",
           "cross_entropy", "differentiable_sample", "forward_backward", "forward_filter", "kl_divergence",
           "max_marginal_path", "posterior_entropy", "sample_posterior", "top_k", "top_level", "validate_inputs",
           "viterbi"]
