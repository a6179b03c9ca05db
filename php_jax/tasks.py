"""The two benchmarks: each an environment module, its hierarchy spec and its supervisor (oracle)."""
from __future__ import annotations

import dataclasses
from types import ModuleType

from php_jax.envs import addition, addition_oracle, nanocraft, nanocraft_oracle
from php_jax.hierarchy import HierarchySpec, Policy


@dataclasses.dataclass(frozen=True)
class Task:
  name: str
  env: ModuleType
  spec: HierarchySpec
  oracle: Policy


TASKS = {
    "addition": Task("addition", addition, addition_oracle.SPEC, addition_oracle.AdditionOracle()),
    "nanocraft": Task("nanocraft", nanocraft, nanocraft_oracle.SPEC, nanocraft_oracle.NanoCraftOracle()),
}


def get(name: str) -> Task:
  if name not in TASKS:
    raise ValueError(f"unknown task {name!r}; choose one of {sorted(TASKS)}")
  return TASKS[name]
