r"""Converts demonstrations between JSON lines and the binary format for large data sets, either way.

  python -m experiments.convert_demos --demos=train.jsonl --hierarchy=H.json --out=train.shards
  python -m experiments.convert_demos --demos=train.shards --hierarchy=H.json --out=train.jsonl

--demos is read as every command reads demonstrations (a directory as a binary set, anything else as JSON
lines) and checked against the hierarchy; --out is written as a binary set of --shard_size demonstrations a
shard where it ends in .shards, else as JSON lines, whole or not at all (a set already there is replaced).
Both read to the same arrays. The demonstrations are converted as they are read, one line or one shard held at a
time. A bad file or flag ends in one line and exit status 2, nothing written. The formats:
docs/own-demonstrations.md.
"""
from __future__ import annotations

import os

from absl import app, flags

from experiments.common import cli
from php_jax.data import demo_files, shards

_DEMOS = flags.DEFINE_string("demos", None, "Demonstrations to convert: JSON lines, or a binary set (a directory).")
_HIERARCHY = flags.DEFINE_string("hierarchy", None, "Their hierarchy file.")
_OUT = flags.DEFINE_string("out", None, "Output: a binary set where it ends in .shards, else JSON lines.")
_SHARD_SIZE = flags.DEFINE_integer("shard_size", shards.SHARD_SIZE, "Demonstrations per shard of a binary --out.",
                                   lower_bound=1)


def size_in_bytes(path: str) -> int:
  """A file's size, or the sum of a directory's files' sizes."""
  if not os.path.isdir(path):
    return os.path.getsize(path)
  return sum(os.path.getsize(os.path.join(path, name)) for name in os.listdir(path))


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    cli.check_outputs({"out": _OUT.value}, {"demos": _DEMOS.value, "hierarchy": _HIERARCHY.value}, demo_sets=True)
    hierarchy = demo_files.read_hierarchy(_HIERARCHY.value)
  except (OSError, ValueError) as e:  # DemoFileError is a ValueError
    cli.fail(str(e))
  counts = {"demonstrations": 0, "annotated": 0, "steps": 0}

  def counted(demonstrations):
    for one in demonstrations:
      counts["demonstrations"] += 1
      counts["annotated"] += one[2] is not None
      counts["steps"] += len(one[1])
      yield one

  try:
    with cli.output_errors("out", _OUT.value):
      demo_files.write_unpadded(_OUT.value, counted(demo_files.iter_demonstrations(_DEMOS.value, hierarchy.spec)),
                                _SHARD_SIZE.value)
  except ValueError as e:  # DemoFileError: --demos is read as it is written
    cli.fail(str(e))
  print(f"{counts['demonstrations']} demonstrations ({counts['annotated']} annotated), {counts['steps']} steps: "
        f"{_DEMOS.value} ({size_in_bytes(_DEMOS.value):,} bytes) -> {_OUT.value} ({size_in_bytes(_OUT.value):,} "
        "bytes)")


if __name__ == "__main__":
  flags.mark_flags_as_required(["demos", "hierarchy", "out"])
  app.run(main, flags_parser=cli.parse_flags)
