r"""Shows a demonstration's call stack as a trained hierarchy decodes it: a call tree in the terminal and,
with --out, a picture.

  python -m experiments.show --policy=DIR [--demos=FILE.jsonl] [--index=N] [--out=FILE.png|svg|html]

--policy is the workdir of any hierarchy's run (`experiments.train` of any task, `experiments.fit`; level-wise
or joint). --demos is any demonstration file of its hierarchy (recorded episodes included); without it, the
run's own training demonstrations (rebuilt from its task and seed, or read from the file it was fitted on).
The decoded stack is the most likely one (exact, whole-stack Viterbi). Where the demonstration carries a
stack (an annotation, or the supervisor's), it is shown beside the decoded one, with their agreement per
level. The picture has one band per level (procedures named, the supervisor's band under the decoded one),
the elementary actions, and per level below the root the posterior probability of each procedure at every
step. A bad flag or file ends in one line and exit status 2 before anything is written.
"""
from __future__ import annotations

from absl import app, flags

from experiments.common import cli, pictures, run_view
from php_jax.data import files

_POLICY = flags.DEFINE_string("policy", None, "Workdir of a trained hierarchy's run.")
_DEMOS = flags.DEFINE_string("demos", None, "Demonstrations (JSON lines, or a binary set). Default: the run's training "
                             "demonstrations.")
_INDEX = flags.DEFINE_integer("index", 0, "Which demonstration (0-based line number).", lower_bound=0)
_OUT = flags.DEFINE_string("out", None, "Picture to write: .png, .svg or .html (the picture and the call trees). "
                           "Default: none, the call trees only.")


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written" if _OUT.value else "nothing written")
  out = _OUT.value
  try:
    if out is not None:
      cli.check_outputs({"out": out}, {"demos": _DEMOS.value, "policy": _POLICY.value})
      if not out.endswith(pictures.SUFFIXES):
        raise ValueError(f"--out={out}: must end in {', '.join(pictures.SUFFIXES)}")
    run = run_view.load(_POLICY.value)
    batch, source = run_view.demonstrations(run, _DEMOS.value)
    if _INDEX.value >= len(batch.length):
      raise ValueError(f"--index={_INDEX.value}: {source} has {len(batch.length)} demonstrations (0.."
                       f"{len(batch.length) - 1})")
  except (OSError, ValueError) as e:  # DemoFileError and CheckpointError are ValueErrors
    cli.fail(str(e))
  [(drawn, lines)] = run_view.decoded(run, batch, [_INDEX.value])
  title = (f"{run.hierarchy.spec.name}: demonstration {_INDEX.value} of {source} "
           f"({int(batch.length[_INDEX.value])} steps)")
  print(title)
  print("\n".join(lines))
  if out is not None:
    data = pictures.save(run_view.figure(run, drawn, title), out, title, "\n".join(lines))
    with cli.output_errors("out", out):
      files.write_atomically(out, data)
    print(f"-> {out}")


if __name__ == "__main__":
  flags.mark_flags_as_required(["policy"])
  app.run(main, flags_parser=cli.parse_flags)
