"""Objects named by import path, "package.module:attribute": a task, an environment or an expert defined
outside php_jax."""
from __future__ import annotations

import importlib


def load_module(name: str, what: str, error: type[ValueError] = ValueError):
  """The module imported by name. Raises `error` (a ValueError) saying why it cannot be imported, `what` naming
  the kind of object looked for in the message ("environment", ...)."""
  try:
    return importlib.import_module(name)
  except Exception as e:  # whatever importing the user's module raises (a command's module: its flags clash)
    raise error(f"cannot load {what} from {name!r}: {_first_line(e)}") from None


def load_attribute(path: str, what: str, error: type[ValueError] = ValueError):
  """The object at "module:attribute". Raises `error` (a ValueError) saying why it cannot be loaded, `what`
  naming the kind of object in the message ("task", "environment", ...)."""
  module_name, colon, attribute = path.partition(":")
  if not (colon and module_name and attribute):
    raise error(f"{what} {path!r} must be module:attribute")
  try:
    return getattr(importlib.import_module(module_name), attribute)
  except Exception as e:  # whatever importing the user's module raises (a command's module: its flags clash)
    raise error(f"cannot load {what} {path!r}: {_first_line(e)}") from None


def _first_line(e: Exception) -> str:
  return f"{type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
