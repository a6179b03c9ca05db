"""php_jax: Parametrized Hierarchical Procedures (Fox et al., ICLR 2018) in JAX."""
__version__ = "0.1.0"  # the one place the version is set (pyproject.toml reads it)

from php_jax.lattice import (NO_FRAME, LatticePath, LatticePosterior, annotate, complete_log_likelihood,
                             forward_backward, max_marginal_path, posterior_entropy, sample_posterior,
                             top_level, viterbi)

__all__ = ["NO_FRAME", "LatticePath", "LatticePosterior", "annotate", "complete_log_likelihood",
           "forward_backward", "max_marginal_path", "posterior_entropy", "sample_posterior", "top_level",
           "viterbi"]
