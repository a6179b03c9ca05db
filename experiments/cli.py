"""What every command shares: a bad flag or input ends in one line on stderr and exit status 2."""
from __future__ import annotations

import sys
from typing import NoReturn

from absl import flags, logging


def fail(message: str) -> NoReturn:
  """Prints "error: message" to stderr and exits with status 2."""
  print(f"error: {message}", file=sys.stderr)
  sys.exit(2)


def seed_list(values: list[str]) -> list[int]:
  """A --seeds flag's values as distinct non-negative integers; ValueError naming them otherwise."""
  if not (values and all(v.isdigit() for v in values) and len(set(map(int, values))) == len(values)):
    raise ValueError(f"--seeds must list distinct non-negative integers; got {','.join(values)}")
  return [int(v) for v in values]


def parse_flags(argv: list[str]) -> list[str]:
  """absl's flag parsing, with a bad flag reported in one line and exit status 2 (for app.run's flags_parser).
  Log messages below warnings (JAX's start-up notes) are not shown unless --verbosity asks for them."""
  try:
    argv = flags.FLAGS(argv)
  except flags.Error as e:
    fail(str(e))
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.WARNING)
  return argv
