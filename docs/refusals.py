"""Writes docs/bad-inputs.md's table of the refusals the tests check, from a recording of them.

  PHP_JAX_RECORD_REFUSALS=/tmp/refusals.jsonl python -m pytest -q -m "not slow" -n 2 --dist loadscope
  python docs/refusals.py /tmp/refusals.jsonl

Each refusal `tests/processes.assert_refused` checks (a command run with bad input: exit status 2, one line on
stderr) is one row: the command, its one-line refusal and the test that holds it. The table sits in the page
between `<!-- refusals: generated -->` and `<!-- end of refusals -->`; the test folders' temporary paths read TMP,
the checkout's paths are relative to it.
"""
from __future__ import annotations

import json
import os
import re
import shlex
import sys

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGE = os.path.join(ROOT, "docs", "bad-inputs.md")
_TABLE = re.compile(r"^<!-- refusals: generated -->\n.*?^<!-- end of refusals -->$", re.M | re.S)
_TEMPORARY = re.compile(r"/tmp/pytest-of-[^/\s]+/pytest-\d+/(?:popen-gw\d+/)?[^/\s'\"]+/?|/tmp/tmp\w+/?")


def _temporary(match: re.Match) -> str:
  return "TMP/" if match[0].endswith("/") else "TMP"


def _portable(text: str) -> str:
  """text with the tests' temporary folders as TMP and the checkout's own paths relative to it."""
  return _TEMPORARY.sub(_temporary, text).replace(ROOT + os.sep, "")


def table(rows: list[dict]) -> str:
  """The Markdown table of recorded refusals: one row per distinct (command, refusal), sorted by command."""
  seen = {}
  for row in rows:
    command = _portable(shlex.join(row["command"]))
    refusal = _portable(row["refusal"])
    test = row["test"].split("[")[0]
    seen.setdefault((command, refusal), test)
  lines = [f"{len(seen)} refusals, each checked by the test named (exit status 2, this one line on stderr, nothing "
           "written):", "", "| command | refusal | test |", "| --- | --- | --- |"]
  for (command, refusal), test in sorted(seen.items()):
    cells = [f"`{command}`", refusal.replace("<", "&lt;").replace(">", "&gt;"), f"`{test}`"]
    lines.append("| " + " | ".join(c.replace("|", "\\|").replace("\n", " ") for c in cells) + " |")
  return "\n".join(lines)


def main(path: str) -> None:
  with open(path, encoding="utf-8") as f:
    rows = [json.loads(line) for line in f if line.strip()]
  with open(PAGE, encoding="utf-8") as f:
    page = f.read()
  if not _TABLE.search(page):
    sys.exit(f"{PAGE}: no <!-- refusals: generated --> ... <!-- end of refusals --> markers")
  page = _TABLE.sub(lambda _: f"<!-- refusals: generated -->\n{table(rows)}\n<!-- end of refusals -->", page)
  with open(PAGE, "w", encoding="utf-8") as f:
    f.write(page)
  print(f"{PAGE}: {len(rows)} recorded refusals")


if __name__ == "__main__":
  if len(sys.argv) != 2:
    sys.exit("usage: python docs/refusals.py RECORDED.jsonl")
  main(sys.argv[1])
