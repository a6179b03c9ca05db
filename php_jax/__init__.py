"""php_jax: Parametrized Hierarchical Procedures (Fox et al., ICLR 2018) in JAX."""
from php_jax.lattice import (NO_FRAME, LatticePath, LatticePosterior, annotate, complete_log_likelihood,
                             forward_backward, max_marginal_path, posterior_entropy, sample_posterior,
                             top_level, viterbi)

__all__ = ["NO_FRAME", "LatticePath", "LatticePosterior", "annotate", "complete_log_likelihood",
           "forward_backward", "max_marginal_path", "posterior_entropy", "sample_posterior", "top_level",
           "viterbi"]
