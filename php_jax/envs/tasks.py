"""The task registry: a task's name → its Task. Adding a task is one module and one line here; a task
defined elsewhere is also reachable by its import path, "package.module:NAME"."""
from __future__ import annotations

from php_jax.envs import addition_task, bubblesort_task, import_path, nanocraft_task
from php_jax.envs.task import Task

TASKS = {task.name: task for task in (addition_task.TASK, nanocraft_task.TASK, bubblesort_task.TASK)}


def get(name: str) -> Task:
  """The registered task `name`, or the Task object at "module:attribute". Raises ValueError."""
  if name in TASKS:
    return TASKS[name]
  module_name, colon, attribute = name.partition(":")
  if colon and module_name and attribute:
    task = import_path.load_attribute(name, "task")
    if isinstance(task, Task):
      return task
    raise ValueError(f"{name!r} is a {type(task).__name__}, not a php_jax Task")
  raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)} or give module:attribute")
