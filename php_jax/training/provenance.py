"""What ran, for results.json: the code's git commit and the versions of the packages and the device."""
from __future__ import annotations

import os
import platform
import subprocess

import flax
import jax
import jaxlib
import optax

import php_jax


def code_version() -> str | None:
  """The git commit that ran, with "+dirty" if php_jax/ or experiments/ had uncommitted changes; None
  outside a git checkout (an installed package)."""
  root = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
  try:
    head = subprocess.run(["git", "rev-parse", "HEAD"], cwd=root, capture_output=True, text=True, check=True)
    status = subprocess.run(["git", "status", "--porcelain", "--", "php_jax", "experiments"], cwd=root,
                            capture_output=True, text=True, check=True)
  except (OSError, subprocess.CalledProcessError):
    return None
  return head.stdout.strip() + ("+dirty" if status.stdout.strip() else "")


def environment_versions() -> dict:
  """What ran, for results.json, with or without a git checkout: the versions of php_jax, Python, jax, jaxlib,
  flax and optax, the device (its platform and kind: "cpu" and "cpu", or "gpu" and the GPU's model name), how
  many devices training split demonstrations over and over how many processes."""
  device = jax.devices()[0]
  return {"php_jax": php_jax.__version__, "python": platform.python_version(), "jax": jax.__version__,
          "jaxlib": jaxlib.__version__, "flax": flax.__version__, "optax": optax.__version__,
          "platform": device.platform, "device_kind": device.device_kind, "devices": jax.device_count(),
          "processes": jax.process_count()}
