"""Test-session settings: a persistent compilation cache in a fresh temporary directory, so that the many
identical computations the training tests compile again (each training run jits its own closures) are
compiled by XLA once per session."""
import tempfile

import jax

jax.config.update("jax_compilation_cache_dir", tempfile.mkdtemp(prefix="php_jax_xla_cache_"))
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
