r"""Writes a finished run's report again (the training commands write it at the end of every run):

  python -m experiments.report --run=DIR

DIR/report.html: one self-contained page with the run's settings and results, its learning curves, its call
graph and three of its training demonstrations decoded and drawn (`experiments.common.run_report`).
"""
from __future__ import annotations

import os

from absl import app, flags

from experiments.common import cli, run_report

_RUN = flags.DEFINE_string("run", None, "A finished run's workdir.")


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"{_RUN.value}/{run_report.REPORT_FILE} not written")
  if not _RUN.value or not os.path.isdir(_RUN.value):
    cli.fail(f"--run={_RUN.value}: not a directory")
  try:
    with cli.output_errors("run", _RUN.value):
      print(f"-> {run_report.write(_RUN.value)}")
  except ValueError as e:  # CheckpointError and DemoFileError are ValueErrors
    cli.fail(str(e))


if __name__ == "__main__":
  flags.mark_flags_as_required(["run"])
  app.run(main, flags_parser=cli.parse_flags)
