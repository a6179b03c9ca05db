"""The E-step: exact inference over the two-level lattice and over the whole call stack (pure JAX)."""
