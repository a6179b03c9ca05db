"""The documents read on the repository as on the site: every relative link reaches its file (and heading),
and the flag tables in the pages are what the commands say today."""
from __future__ import annotations

import glob
import os
import re
import sys
import unicodedata

import pytest

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
sys.path.insert(0, os.path.join(ROOT, "docs"))
import hooks  # noqa: E402  (docs/ is not a package)

_LINK = re.compile(r"\]\(([^)\s]+)\)")
_FENCE = re.compile(r"^```.*?^```", re.M | re.S)
_INLINE_CODE = re.compile(r"`[^`\n]*`")


def _documents() -> list[str]:
  found = ["README.md", "RESULTS.md", "BUILD.md", *glob.glob("docs/**/*.md", root_dir=ROOT, recursive=True),
           *glob.glob("examples/*/README.md", root_dir=ROOT)]
  return sorted(found)


def _slug(heading: str) -> str:
  """A heading's anchor as the site makes it (Python-Markdown's toc) and, for plain headings, GitHub."""
  text = unicodedata.normalize("NFKD", re.sub(r"[`*]", "", heading)).encode("ascii", "ignore").decode()
  return re.sub(r"[-\s]+", "-", re.sub(r"[^\w\s-]", "", text).strip().lower())


def _anchors(path: str) -> set[str]:
  with open(path, encoding="utf-8") as f:
    text = _FENCE.sub("", f.read())
  return {_slug(line.lstrip("#")) for line in text.splitlines() if re.match(r"#{1,6} ", line)}


def _links(path: str) -> list[str]:
  with open(os.path.join(ROOT, path), encoding="utf-8") as f:
    text = _INLINE_CODE.sub("", _FENCE.sub("", f.read()))
  return [t for t in _LINK.findall(text) if "://" not in t and not t.startswith("mailto:")]


@pytest.mark.parametrize("document", _documents())
def test_every_relative_link_reaches_its_file_and_heading(document):
  for link in _links(document):
    target, _, anchor = link.partition("#")
    path = os.path.normpath(os.path.join(ROOT, os.path.dirname(document), target)) if target else os.path.join(
        ROOT, document)
    assert os.path.exists(path), f"{document}: the link ({link}) names {os.path.relpath(path, ROOT)}, which is not there"
    if anchor and path.endswith(".md"):
      assert anchor in _anchors(path), f"{document}: the link ({link}) names a heading {os.path.relpath(path, ROOT)} lacks"


def test_site_links_are_the_repository_links_moved_with_their_pages():
  assert hooks.site_link("docs/index.md", "index.md", "../RESULTS.md") == "RESULTS.md"
  assert hooks.site_link("docs/notes/a.md", "notes/a.md", "../../BUILD.md") == "../BUILD.md"
  assert hooks.site_link("RESULTS.md", "RESULTS.md", "docs/training.md") == "training.md"
  assert hooks.site_link("RESULTS.md", "RESULTS.md", "results/addition.png") == "results/addition.png"
  assert hooks.site_link("docs/seeing.md", "seeing.md", "outputs.md") == "outputs.md"
  assert hooks.site_link("docs/tasks.md", "tasks.md", "../examples/nanocraft.jsonl") == "../examples/nanocraft.jsonl"


def test_the_flag_tables_in_the_pages_are_the_commands_flags_today():
  tables = []
  for path in glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True):
    with open(path, encoding="utf-8") as f:
      tables += [(path, module, table) for module, table in hooks._FLAG_TABLE.findall(f.read())]
  assert {module for _, module, _ in tables} >= {"experiments.train", "experiments.fit"}
  for path, module, table in tables:
    assert table.strip() == hooks.flag_table(module), f"{path}: run `python docs/hooks.py` to rewrite {module}'s table"
