"""What every demonstration reader checks, whatever its file's format (JSON lines: `demo_files`; binary:
`shards`): the error it raises, the observation size, actions in their factors' ranges and the call-stack
rules of an annotated stack, each with the same words in both."""
from __future__ import annotations

import dataclasses

import numpy as np

from php_jax import demos as demos_lib
from php_jax.hierarchy import HierarchySpec


class DemoFileError(ValueError):
  """A malformed demonstration or hierarchy file; the message starts with the path (and line)."""


def observation_size_error(size: int, spec: HierarchySpec) -> ValueError:
  """Observations of size numbers where spec's have spec.obs_dim."""
  return ValueError(f"observations have {size} numbers where the hierarchy's have {spec.obs_dim} (a file of another "
                    "hierarchy or environment)")


def action_error(t: int, factor: int, value: int, sizes: tuple[int, ...]) -> ValueError:
  """Action t's factor taking a value outside its range."""
  return ValueError(f"action {t}: factor {factor} = {value} is outside 0..{sizes[factor] - 1} (the hierarchy's "
                    f"action factor sizes are {list(sizes)})")


def counter_error(t: int, level: int, counter: int) -> ValueError:
  """A counter beyond its step t."""
  return ValueError(f"stack step {t}, level {level}: counter {counter} is outside 0..{t} (a procedure runs at "
                    "most one operation per step)")


def check_stack(procs: np.ndarray, taus: np.ndarray, spec: HierarchySpec) -> None:
  """Raises ValueError ("stack ...") where an annotated stack [T, d] (UNKNOWN where unknown) breaks the
  call-stack rules (`demos.stack_error`) or gives a counter beyond its step."""
  error = demos_lib.stack_error(procs, taus, spec)
  if error:
    raise ValueError(f"stack {error}")
  late = np.argwhere(taus > np.arange(len(taus))[:, None])
  if late.size:
    t, level = late[0]
    raise counter_error(t, level, taus[t, level])


def fitted_spec(path: str, spec: HierarchySpec, obs_dim: int) -> HierarchySpec:
  """spec with the observation size a file's demonstrations show; DemoFileError naming the file where the
  hierarchy's "observes" names an entry they do not have."""
  try:
    return dataclasses.replace(spec, obs_dim=obs_dim)
  except ValueError as e:
    raise DemoFileError(f"{path}: the hierarchy does not fit these demonstrations: {e}") from None
