"""Settings for a pytest run: a persistent compilation cache in a fresh temporary directory, so that the many
identical computations the training tests compile again (each training run jits its own closures) are
compiled by XLA once per run, and removed at the end of the run; with pytest-xdist (`-n 2`), the workers
share the cache of the process that started them. XLA without LLVM's optimizations, with its older CPU
fusion emitters. Also puts the checkout on the PYTHONPATH of the commands the tests run: experiments/ is not
installed, and `python -m experiments.X` must find it whatever the working directory. With
PHP_JAX_RECORD_REFUSALS set, every refusal a test's command gives is recorded
(`tests.processes.record_refusal`)."""
import os
import pathlib
import shutil
import subprocess
import tempfile

import jax
import pytest

from tests import processes

ROOT = str(pathlib.Path(__file__).resolve().parents[1])
os.environ["PYTHONPATH"] = os.pathsep.join([ROOT, *filter(None, [os.environ.get("PYTHONPATH")])])

WORKER = "PYTEST_XDIST_WORKER" in os.environ  # a pytest-xdist worker: its parent made the cache and removes it
CACHE = os.environ["JAX_COMPILATION_CACHE_DIR"] if WORKER else tempfile.mkdtemp(prefix="php_jax_xla_cache_")
jax.config.update("jax_compilation_cache_dir", CACHE)
jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
jax.config.update("jax_persistent_cache_min_entry_size_bytes", 0)
# The commands the tests run share the cache: each compiles the same programs as the others.
os.environ.update(JAX_COMPILATION_CACHE_DIR=CACHE, JAX_PERSISTENT_CACHE_MIN_COMPILE_TIME_SECS="0",
                  JAX_PERSISTENT_CACHE_MIN_ENTRY_SIZE_BYTES="0")
# XLA compiles without LLVM's optimizations and with its older CPU fusion emitters (in this process, whose
# backend starts after this, and in the commands): compiling is most of the suite's time, and the two take a
# third of it off; the tests' programs are small (`processes.fit_recorded`'s learning runs turn the
# optimizations back on). Settings given in XLA_FLAGS come after, so that they win. A worker has its parent's.
if not WORKER:
  os.environ["XLA_FLAGS"] = " ".join(filter(None, ["--xla_backend_optimization_level=0",
                                                   "--xla_cpu_use_fusion_emitters=false",
                                                   os.environ.get("XLA_FLAGS")]))


def pytest_sessionfinish(session, exitstatus):
  """Leaves nothing behind in the temporary directory: the cache goes with the run."""
  if not WORKER:
    shutil.rmtree(CACHE, ignore_errors=True)


@pytest.fixture(autouse=True)
def _record_refusals(monkeypatch):
  """With PHP_JAX_RECORD_REFUSALS set, subprocess.run records each command's refusal as it returns."""
  if not os.environ.get(processes.RECORD_REFUSALS):
    return
  run = subprocess.run

  def recorded(command, *args, **kwargs):
    proc = run(command, *args, **kwargs)
    processes.record_refusal(command, proc)
    return proc

  monkeypatch.setattr(subprocess, "run", recorded)
