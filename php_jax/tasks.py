"""The task registry: a task's name → its Task. Adding a task is one module and one line here; a task
defined elsewhere is also reachable by its import path, "package.module:NAME"."""
from __future__ import annotations

import importlib

from php_jax.envs import addition_task, bubblesort_task, nanocraft_task
from php_jax.task import Task

TASKS = {task.name: task for task in (addition_task.TASK, nanocraft_task.TASK, bubblesort_task.TASK)}


def get(name: str) -> Task:
  """The registered task `name`, or the Task object at "module:attribute". Raises ValueError."""
  if name in TASKS:
    return TASKS[name]
  module_name, colon, attribute = name.partition(":")
  if colon and module_name and attribute:
    try:
      task = getattr(importlib.import_module(module_name), attribute)
    except Exception as e:  # whatever importing the user's module raises (a command's module: its flags clash)
      raise ValueError(f"cannot load task {name!r}: {type(e).__name__}: {str(e).splitlines()[0] if str(e) else ''}"
                       ) from None
    if isinstance(task, Task):
      return task
    raise ValueError(f"{name!r} is a {type(task).__name__}, not a php_jax Task")
  raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)} or give module:attribute")
