r"""Decodes demonstrations with a fitted hierarchy: per demonstration its log-likelihood, its most likely
call stack at every step, and whether the hierarchy replays it.

  python -m experiments.decode --policy=DIR --demos=IN.jsonl --out=OUT.jsonl

--policy is a workdir of `experiments.fit` (or of `experiments.train`). Each output line, in input order:

  {"log_likelihood": float or null,     log P(actions | observations), summed over every call stack (null
                                        where no call stack fits the demonstration within the hierarchy's call
                                        graph and the counter capacities it was trained with)
   "stack": [[[h, tau], ...], ...],     per step, root first: the most likely stack (exact, whole-stack
                                        Viterbi; null where log_likelihood is)
   "replayed": bool,                    the argmax policy, run on the recorded observations, takes every
                                        recorded action and its root returns after the last (where its
                                        demonstrations' environment ended them, every action is enough); the
                                        policy runs without counter capacities, so a demonstration longer than
                                        the training ones can replay with a null log_likelihood
   "first_mismatch": int or null}       the first step where it does not (null when replayed)

It prints how many replay, the demonstrations' log-likelihood per step (an unsupervised score: of
held-out demonstrations, a way to compare runs or restarts without an environment), and per level how many
calls of each procedure the decoded stacks make (a procedure never called is one the hierarchy does not
need for these demonstrations). Stacks in the input are
not used for decoding; where they are given, the agreement of the decoded stacks with them is printed per
level (exact, and up to a renaming of each level's procedures), over the demonstrations some stack fits. A
bad flag or a malformed line ends in one line and exit status 2 before anything runs; the output is written
atomically. The file formats: docs/own-demonstrations.md.
"""
from __future__ import annotations

import json

import numpy as np
from absl import app, flags

from experiments.common import cli
from php_jax.analysis import decoding
from php_jax.data import agreement, call_tree, demo_files, files, views
from php_jax.envs import replay
from php_jax.model import PHPHierarchy
from php_jax.training import checkpoint

_POLICY = flags.DEFINE_string("policy", None, "Workdir holding a fitted hierarchy.")
_DEMOS = flags.DEFINE_string("demos", None, "Demonstrations to decode: JSON lines, or a binary set (a directory).")
_OUT = flags.DEFINE_string("out", None, "Output JSON-lines file.")
_BATCH_SIZE = flags.DEFINE_integer("batch_size", 512, "Demonstrations decoded together.", lower_bound=1)


def decode_lines(hierarchy: PHPHierarchy, capacity, batch) -> tuple[list[dict], decoding.Decoded]:
  """The output lines of a batch of demonstrations, and the decoded stacks."""
  decoded = decoding.decode(hierarchy, capacity, batch, chunk=_BATCH_SIZE.value)
  replayed = replay.replay(hierarchy, hierarchy.spec, batch)
  lines = []
  for b, n in enumerate(np.asarray(batch.length)):
    stack = np.stack([decoded.procedures[b, :n], decoded.counters[b, :n]], axis=-1).tolist()
    mismatch = int(replayed.first_mismatch[b])
    log_likelihood = float(decoded.log_likelihood[b])
    fits = np.isfinite(log_likelihood)
    lines.append({"log_likelihood": log_likelihood if fits else None, "stack": stack if fits else None,
                  "replayed": bool(replayed.replayed[b]), "first_mismatch": None if mismatch < 0 else mismatch})
  return lines, decoded


def main(argv):
  if argv[1:]:
    cli.fail(f"unexpected arguments: {' '.join(argv[1:])}")
  cli.exit_on_interrupt(f"--out={_OUT.value} not written")
  try:
    cli.check_outputs({"out": _OUT.value}, {"demos": _DEMOS.value, "policy": _POLICY.value})
    _, hierarchy = checkpoint.load_policy(_POLICY.value)
    capacity = checkpoint.saved_capacity(_POLICY.value)
    if not isinstance(hierarchy, PHPHierarchy) or capacity is None:
      raise ValueError(f"--policy={_POLICY.value} holds no hierarchy with its counter capacities (a flat baseline, "
                       "or a model saved before they were recorded)")
    batch, _ = demo_files.read_demonstrations(_DEMOS.value, hierarchy.spec)
  except (OSError, ValueError) as e:  # DemoFileError and CheckpointError are ValueErrors
    cli.fail(str(e))
  lines, decoded = decode_lines(hierarchy, capacity, batch)
  with cli.output_errors("out", _OUT.value):
    files.write_atomically(_OUT.value, "".join(json.dumps(line) + "\n" for line in lines).encode())
  replayed = sum(line["replayed"] for line in lines)
  print(f"{hierarchy.spec.name}: {replayed}/{len(lines)} replayed -> {_OUT.value}")
  per_step, unfit = decoding.log_likelihood_per_step(decoded.log_likelihood, np.asarray(batch.length))
  print(f"log-likelihood: {'none' if per_step is None else f'{per_step:.4f} per step'}"
        + (f"; {unfit} of {len(lines)} demonstrations fit no call stack" if unfit else ""))
  spec = hierarchy.spec
  fits = np.isfinite(decoded.log_likelihood)  # the stacks of demonstrations that fit none mean nothing
  if not fits.any():
    return
  used = call_tree.calls_per_procedure(decoded.procedures[fits], decoded.counters[fits],
                                       np.asarray(batch.length)[fits],
                                       [spec.num_procs(level) for level in range(spec.num_levels)])
  for level in range(1, spec.num_levels):
    calls = ", ".join(f"{name} {n}" for name, n in zip(spec.levels[level], used[level]))
    unused = int(np.sum(used[level] == 0))
    print(f"level {level} calls: {calls}" + (f"; {unused} of {spec.num_procs(level)} procedures never called"
                                              if unused else ""))
  given = views.select(batch, fits)
  procs, counters = decoded.procedures[fits], decoded.counters[fits]
  over = f" (over the {int(fits.sum())} of {len(lines)} demonstrations some stack fits)" if unfit else ""
  for level in range(1, spec.num_levels):
    measured = agreement.stack_agreement(given.procedures, given.counters, procs, counters, level)
    if measured:
      exact, renamed = measured
      boundaries = agreement.stack_boundary_scores(given.procedures, given.counters, procs, counters,
                                                   given.length, level)
      found = f"; call boundaries: F1 {boundaries['f1']:.3f}" if boundaries else ""
      procedures = agreement.stack_procedure_agreement(given.procedures, procs, level)
      print(f"level {level}: decoded stacks agree with the given ones on {exact:.3f} of annotated steps "
            f"({renamed:.3f} up to renaming; procedures alone, renamed: {procedures:.3f}){found}{over}")


if __name__ == "__main__":
  flags.mark_flags_as_required(["policy", "demos", "out"])
  app.run(main, flags_parser=cli.parse_flags)
