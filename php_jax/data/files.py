"""Writing a file whole or not at all: readers see the old file or the new one, never part of one."""
from __future__ import annotations

import contextlib
import os
import secrets
import threading

import jax

WRITING = threading.RLock()  # held while write_atomically or a whole checkpoint save writes (reentrant: a save
# holds it around its own write_atomically calls); whoever ends the process waits for it


def write_atomically(path: str, data: bytes) -> None:
  """Writes data to path through a temporary file in the same directory renamed into place: readers see the
  old file or the new one, never part of one. A path that is a symbolic link writes the file it names (as a
  shell's `>` would), the link left as it is. The file gets mode 0o666 & ~umask (0644 under umask 022), as
  open() would give it; if the write or the rename fails (KeyboardInterrupt included) the temporary file is
  removed. Holds WRITING meanwhile. Of several processes (jax.distributed), only the first writes: the
  others hold the same data."""
  if jax.process_index() != 0:
    return
  path = os.path.realpath(path)
  directory = os.path.dirname(path)
  with WRITING:
    os.makedirs(directory, exist_ok=True)
    while True:  # O_CREAT | O_EXCL with mode 0o666: the kernel applies the umask, no need to read or change it
      tmp = os.path.join(directory, f".{os.path.basename(path)}.{secrets.token_hex(6)}.tmp")
      try:
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o666)
        break
      except FileExistsError:
        continue
    try:
      with os.fdopen(fd, "wb") as f:
        f.write(data)
      os.replace(tmp, path)
    except BaseException:
      with contextlib.suppress(OSError):
        os.unlink(tmp)
      raise
