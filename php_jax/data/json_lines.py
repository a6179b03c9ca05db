"""Bounded JSON for the file readers (demonstrations, hierarchies, problems).

A value is refused, with a ValueError, when its text is longer than MAX_LINE_BYTES, nests arrays and objects
deeper than MAX_DEPTH, writes NaN or ±Infinity, holds a number (integers included) beyond float32's range
(±3.4e38), or repeats a key in one object: no line can exhaust the stack or memory or stand for a number the
models cannot hold. Readers add their own checks (types, integer ranges) and their "PATH:LINE:" prefix.
"""
from __future__ import annotations

import json
import re
from collections.abc import Iterator
from typing import BinaryIO

import numpy as np

MAX_LINE_BYTES = 1 << 26  # 64 MiB, the newline included
MAX_DEPTH = 32
FLOAT32_MAX = float(np.finfo(np.float32).max)

_ESCAPE = re.compile(rb"\\.", re.DOTALL)
_STRING = re.compile(rb'"[^"]*"')
_NOT_BRACKETS = bytes(sorted(set(range(256)) - set(b"[]{}")))
_STEPS = bytes.maketrans(b"[]{}", b"\x01\xff\x01\xff")  # +1 opens a level, -1 (as int8) closes one
_CHUNK = 1 << 20
_MAX_INT_CHARS = 40  # a sign and the 39 digits of float32's largest value


class JSONBoundsError(ValueError):
  """A line or value outside the bounds (its JSON may well be valid)."""


def lines(f: BinaryIO) -> Iterator[tuple[int, bytes]]:
  """(number from 1, line) of every line of a binary file that is not blank (ASCII whitespace). A line
  longer than MAX_LINE_BYTES comes cut to MAX_LINE_BYTES + 1 bytes, for `loads` to refuse."""
  number = 0
  while line := f.readline(MAX_LINE_BYTES + 1):
    number += 1
    cut = len(line) > MAX_LINE_BYTES and not line.endswith(b"\n")
    if cut or line.strip():
      yield number, line
    while cut:
      rest = f.readline(MAX_LINE_BYTES + 1)
      cut = len(rest) > MAX_LINE_BYTES and not rest.endswith(b"\n")


def loads(raw: bytes):
  """The JSON value of raw (a line, or a whole file). Raises UnicodeDecodeError if raw is not UTF-8,
  JSONSyntaxError if it is not JSON, and JSONBoundsError if it is outside the bounds."""
  if len(raw) > MAX_LINE_BYTES:
    raise JSONBoundsError(f"longer than {MAX_LINE_BYTES} bytes")
  text = raw.decode("utf-8")
  if _deeper_than(raw, MAX_DEPTH):
    raise JSONBoundsError(f"arrays and objects nested deeper than {MAX_DEPTH}")
  try:
    return json.loads(text, parse_constant=_constant, parse_float=_float, parse_int=_int,
                      object_pairs_hook=_object)
  except json.JSONDecodeError as e:
    raise JSONSyntaxError(_where(e) + e.msg) from None


class JSONSyntaxError(ValueError):
  """Text that is not JSON; the message says where, within a line by its column only."""


def _where(e: json.JSONDecodeError) -> str:
  """"not JSON at column C: " for an error in a text of one line (its line number is the reader's to give),
  "not JSON, it ends too soon: " past its last character, else "not JSON at line L, column C: "."""
  body = e.doc.rstrip("\r\n")
  if e.pos >= len(body.rstrip()):
    return "not JSON, it ends too soon: "
  if "\n" in body:
    return f"not JSON at line {e.lineno}, column {e.colno}: "
  return f"not JSON at column {e.colno}: "


def _deeper_than(raw: bytes, depth: int) -> bool:
  """Whether raw's arrays and objects, outside strings, nest deeper than depth (UTF-8 keeps every byte of
  '"', '\\' and brackets for those characters alone)."""
  brackets = _STRING.sub(b"", _ESCAPE.sub(b"", raw)).translate(None, _NOT_BRACKETS)
  if len(brackets) <= depth:
    return False
  steps = np.frombuffer(brackets.translate(_STEPS), np.int8)
  level = 0
  for start in range(0, len(steps), _CHUNK):
    running = level + np.cumsum(steps[start:start + _CHUNK], dtype=np.int64)
    if running.max() > depth:
      return True
    level = int(running[-1])
  return False


def shown(value) -> str:
  """value's repr for a message, shortened past 40 characters."""
  return _shown(repr(value))


def _shown(text: str) -> str:
  return text if len(text) <= 40 else f"{text[:24]}...{text[-8:]} ({len(text)} characters)"


def _constant(name: str):
  raise JSONBoundsError(f"{name} is not a finite number")


def _float(text: str) -> float:
  value = float(text)
  if not abs(value) <= FLOAT32_MAX:
    raise _range_error(text)
  return value


def _int(text: str) -> int:
  if len(text) > _MAX_INT_CHARS or abs(value := int(text)) > FLOAT32_MAX:
    raise _range_error(text)
  return value


def _range_error(text: str) -> JSONBoundsError:
  return JSONBoundsError(f"number {_shown(text)} is beyond ±3.4e38 (float32's range)")


def _object(pairs: list) -> dict:
  obj = dict(pairs)
  if len(obj) < len(pairs):
    seen = set()
    for key, _ in pairs:
      if key in seen:
        raise JSONBoundsError(f"key {shown(key)} appears twice in one object")
      seen.add(key)
  return obj


def check_keys(obj: dict, known: tuple[str, ...], kind: str = "problem") -> None:
  """For a line's object (a task's parse_problem, the demonstration and hierarchy files): raises ValueError naming the first key of a line's
  object not in known."""
  for key in obj:
    if key not in known:
      raise ValueError(f"unknown key {shown(key)}; a {kind} has {', '.join(map(repr, known))}")
