"""What every command shares: a bad flag or input ends in one line on stderr and exit status 2; Ctrl-C or
SIGTERM in one line and exit status 130, at once, whatever is being computed."""
from __future__ import annotations

import contextlib
import os
import re
import signal
import sys
import tempfile
import textwrap
import threading
from typing import NoReturn

from absl import flags, logging

from experiments.common.flag_groups import GROUPS
from php_jax.data import files, shards
from php_jax.training import checkpoint
from php_jax.training.run import RUN_FILES
from php_jax.training.selection import CANDIDATES_DIR

RUN_FOLDERS = (checkpoint.MODEL_DIR, checkpoint.TRAINING_DIR, CANDIDATES_DIR)  # what a run writes below its workdir


def fail(message: str) -> NoReturn:
  """Prints "error: message" to stderr, on one line (a newline inside it, say in a path, written as \\n), and
  exits with status 2. Holds files.WRITING meanwhile: where an interrupt is ending the process (and deleting a
  partial file, which a write may then fail on), that ending is the one printed."""
  with files.WRITING:
    print(f"error: {message}".replace("\r", "\\r").replace("\n", "\\n"), file=sys.stderr)
    sys.exit(2)


def exit_on_interrupt(message: str) -> None:
  """From now on, SIGINT (Ctrl-C) or SIGTERM ends the command within moments, even inside a long compiled
  computation (which Python's own handling would wait out): "interrupted: message" on stderr, exit status 130.
  A file being written (`files.write_atomically`) is first put in place; one being filled from a stream
  (`files.write_streamed`, `shards.write_shards`) is deleted. Call it from the main thread.

  The signals' handlers only wake a watcher thread through the wakeup fd, which the kernel-level handler
  writes to in whichever thread receives the signal; the watcher ends the process."""
  read, write = os.pipe()
  os.set_blocking(write, False)
  signal.set_wakeup_fd(write)
  for signum in (signal.SIGINT, signal.SIGTERM):
    signal.signal(signum, lambda *_: None)

  def watch():
    os.read(read, 1)
    with files.WRITING:
      files.remove_partial()
      if sys.stdout.isatty():  # a live progress display hid the cursor
        print("\x1b[?25h", flush=True)
      print(f"interrupted: {message}", file=sys.stderr, flush=True)
      os._exit(130)

  threading.Thread(target=watch, name="interrupt watcher", daemon=True).start()


def check_outputs(outputs: dict[str, str | None], inputs: dict[str, str | None], make_folders: bool = False,
                  demo_sets: bool = False) -> None:
  """Raises ValueError naming the flag of the first output ({flag: path}; None: not asked for) that could
  not be written, before any work: an empty path, a directory, a file in a missing (unless make_folders: the
  command makes it) or unwritable directory, one of the inputs ({flag: path}; a --policy workdir's flag: the
  files its run wrote, and anything inside the folders it wrote) or another output, or a path inside one of
  them. demo_sets: an output ending in shards.SUFFIX is a binary demonstration set, which replaces a set there
  but nothing else."""
  seen, run_folders = {}, []
  for flag, path in inputs.items():
    if flag == "policy" and path:
      seen.update({f"policy={path}:{name}": os.path.join(path, name) for name in RUN_FILES})
      run_folders += [(path, name) for name in RUN_FOLDERS]
    else:
      seen[flag] = path
  for flag, path in outputs.items():
    if path is None:
      continue
    if not path:
      raise ValueError(f"--{flag}: must name a file; got ''")
    if demo_sets and shards.write_as_binary(path):
      if os.path.lexists(path) and not shards.is_set(path):
        raise ValueError(f"--{flag}={path}: something that is not a demonstration set is there; not replaced")
    elif os.path.isdir(path):
      raise ValueError(f"--{flag}={path} is a directory")
    directory = os.path.dirname(os.path.realpath(path))  # a symbolic link writes the file it names
    while make_folders and not os.path.exists(directory):  # the folder that making it would write in
      directory = os.path.dirname(directory)
    if not os.path.exists(directory):
      raise ValueError(f"--{flag}={path}: directory {directory} does not exist")
    if not os.path.isdir(directory):
      raise ValueError(f"--{flag}={path}: {directory} is a file, not a directory")
    if not os.access(directory, os.W_OK | os.X_OK):
      raise ValueError(f"--{flag}={path}: directory {directory} is not writable")
    for policy, name in run_folders:
      if _inside(path, os.path.join(policy, name)):
        raise ValueError(f"--{flag}={path} is inside {name}/ of --policy={policy}, which its run wrote: write "
                         "elsewhere")
    for other, other_path in seen.items():
      if other_path and _inside(path, other_path):
        raise ValueError(f"--{flag}={path} is inside --{other}={other_path}")
      if other_path and same_file(path, other_path):
        if other.startswith("policy="):
          kind = "model" if os.path.basename(other_path) in checkpoint.MODEL_FILES else "run's"
          raise ValueError(f"--{flag}={path} is the {kind} file {other_path} of --{other.rsplit(':', 1)[0]}")
        raise ValueError(f"--{flag}={path} is the {'input file' if other in inputs else 'same file as'} "
                         f"--{other}={other_path}")
    seen[flag] = path


def writable_folder(flag: str, path: str) -> None:
  """Makes the folder path (and those above it) and proves that files can be written there, by writing and
  removing one; otherwise ends the command in one line naming the flag (exit status 2): a read-only file
  system, a file in the way, no permission."""
  try:
    os.makedirs(path, exist_ok=True)
    with tempfile.NamedTemporaryFile(dir=path, prefix=".write-check-"):
      pass
  except OSError as e:
    fail(f"--{flag}={path}: cannot write there: {e.strerror or e}")


def same_file(a: str, b: str) -> bool:
  """Whether paths a and b name one file: the same after symbolic links, or hard links to one file."""
  return os.path.realpath(a) == os.path.realpath(b) or (
      os.path.exists(a) and os.path.exists(b) and os.path.samefile(a, b))


def _inside(path: str, folder: str) -> bool:
  """Whether path lies below folder (symbolic links followed)."""
  return os.path.realpath(path).startswith(os.path.realpath(folder) + os.sep)


@contextlib.contextmanager
def output_errors(flag: str, path: str):
  """Ends the command in one line naming the flag (exit status 2) if writing its file fails in the block (a
  full disk, a file system made read-only); `files.write_atomically` leaves nothing behind."""
  try:
    yield
  except OSError as e:
    fail(f"--{flag}={path}: cannot write: {e.strerror or e}")


def seed_list(values: list[str]) -> list[int]:
  """A --seeds flag's values as distinct non-negative integers; ValueError naming them otherwise."""
  if not (values and all(v.isdigit() for v in values) and len(set(map(int, values))) == len(values)):
    raise ValueError(f"--seeds must list distinct non-negative integers; got {','.join(values)}")
  return [int(v) for v in values]


_HELP = {"--help", "-help", "-h", "-?", "--helpshort", "--helpfull", "--helpxml"}
def parse_flags(argv: list[str]) -> list[str]:
  """absl's flag parsing, with a bad flag reported in one line and exit status 2 (for app.run's flags_parser),
  and --help or -h printing the command's usage and its flags grouped by what they set, exit status 0
  (--helpfull: absl's own list, with its logging flags). Log messages below warnings (JAX's start-up notes)
  are not shown unless --verbosity asks for them."""
  if set(argv[1:]) & {"--help", "-help", "-h", "-?", "--helpshort"}:
    try:
      print(grouped_help(argv[0]), flush=True)
    except BrokenPipeError:  # a reader that stopped early (`| head`): the rest goes nowhere, quietly
      os.dup2(os.open(os.devnull, os.O_WRONLY), sys.stdout.fileno())
    sys.exit(0)
  try:
    argv = flags.FLAGS(argv)
  except flags.Error as e:
    fail(str(e))
  except SystemExit as e:
    if e.code == 1 and set(argv[1:]) & _HELP:
      sys.exit(0)
    raise
  if not flags.FLAGS["verbosity"].present:
    logging.set_verbosity(logging.WARNING)
  return argv


def grouped_help(program: str) -> str:
  """The command's docstring, then its flags: its own first, then each group it shares with other commands
  (training settings, the run, the environment), each flag with its default and help."""
  module = sys.modules["__main__"]
  defined = {}
  for flag in flags.FLAGS.get_key_flags_for_module(program):
    source = flags.FLAGS.find_module_defining_flag(flag.name, default=program)
    defined.setdefault(GROUPS.get(source, "flags of this command"), []).append(flag)
  order = ["flags of this command", *GROUPS.values()]
  parts = [(module.__doc__ or "").strip(), ""]
  for group in sorted(defined, key=order.index):
    parts.append(f"{group[0].upper()}{group[1:]}:")
    for flag in sorted(defined[group], key=lambda f: f.name):
      name = f"--[no]{flag.name}" if flag.boolean else f"--{flag.name}"
      stated = flag.default is None or "Default: " in flag.help
      default = "" if stated else f" (default: {flag.default_as_str.strip(chr(39))})"
      parts.append(textwrap.fill(f"{flag.help}{default}", width=100, initial_indent=f"  {name}: ",
                                 subsequent_indent="      "))
    parts.append("")
  pages = sorted(set(re.findall(r"docs/[\w./-]+\.md", module.__doc__ or "")))
  if pages:
    parts.append(f"Documentation: {', '.join(pages)}.")
  parts.append("--helpfull lists absl's own flags too (logging, --flagfile).")
  return "\n".join(parts)
