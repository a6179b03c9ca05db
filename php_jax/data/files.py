"""Writing a file whole or not at all: readers see the old file or the new one, never part of one."""
from __future__ import annotations

import contextlib
import os
import secrets
import shutil
import threading
from typing import BinaryIO, Iterable

import jax

WRITING = threading.RLock()  # held while write_atomically or a whole checkpoint save writes (reentrant: a save
# holds it around its own write_atomically calls); whoever ends the process waits for it
PARTIAL: set[str] = set()  # temporary files and directories being filled from a stream; `remove_partial` deletes them


def write_atomically(path: str, data: bytes) -> None:
  """Writes data to path through a temporary file in the same directory renamed into place: readers see the
  old file or the new one, never part of one. A path that is a symbolic link writes the file it names (as a
  shell's `>` would), the link left as it is. The file gets mode 0o666 & ~umask (0644 under umask 022), as
  open() would give it; if the write or the rename fails (KeyboardInterrupt included) the temporary file is
  removed. Holds WRITING meanwhile. Of several processes (jax.distributed), only the first writes: the
  others hold the same data."""
  if jax.process_index() != 0:
    return
  with WRITING:
    path, tmp, f, made = _temporary(path)
    try:
      with f:
        f.write(data)
      os.replace(tmp, path)
    except BaseException:
      _remove(tmp, made)
      raise


def write_streamed(path: str, chunks: Iterable[bytes]) -> None:
  """write_atomically for data made while it is written (chunks, a generator that may run for hours: a
  recording): the temporary file is filled chunk by chunk while listed in PARTIAL, so that an interrupt
  meanwhile ends the process at once and `remove_partial` deletes it; WRITING is held only for the rename."""
  if jax.process_index() != 0:
    return
  with WRITING:  # an interrupt finds the file listed as soon as it exists
    path, tmp, f, made = _temporary(path)
    PARTIAL.add(tmp)
  try:
    with f:
      for chunk in chunks:
        f.write(chunk)
    with WRITING:
      os.replace(tmp, path)
      PARTIAL.discard(tmp)
  except BaseException:
    _remove(tmp, made)
    PARTIAL.discard(tmp)
    raise


def remove_partial() -> None:
  """Deletes every temporary file and directory of PARTIAL (for whoever ends the process, holding WRITING)."""
  for path in list(PARTIAL):
    if os.path.isdir(path):
      shutil.rmtree(path, ignore_errors=True)
    else:
      with contextlib.suppress(OSError):
        os.unlink(path)
    PARTIAL.discard(path)


def _temporary(path: str) -> tuple[str, str, BinaryIO, list[str]]:
  """(path resolved through symbolic links, a new temporary file beside it, that file open for writing, the
  folders made for it, deepest first): mode 0o666 & ~umask (O_CREAT | O_EXCL: the kernel applies the umask),
  its folder made if missing."""
  path = os.path.realpath(path)
  directory = os.path.dirname(path)
  made, missing = [], directory
  while not os.path.exists(missing):
    made.append(missing)
    missing = os.path.dirname(missing)
  os.makedirs(directory, exist_ok=True)
  while True:
    tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
    try:
      return path, tmp, os.fdopen(os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666), "wb"), made
    except FileExistsError:
      continue


def _remove(tmp: str, made: list[str]) -> None:
  """Removes a failed write's temporary file and the folders made for it (those still empty)."""
  with contextlib.suppress(OSError):
    os.unlink(tmp)
  for folder in made:
    with contextlib.suppress(OSError):
      os.rmdir(folder)
