"""mkdocs hooks, and the writer of the pages' flag tables.

RESULTS.md, BUILD.md, the examples' READMEs and the figures in results/ become pages and files of the site.
Pages link as the repository lays them out (docs/training.md to `../RESULTS.md`, RESULTS.md to
`docs/training.md`), so that links work when read on the repository; the site moves RESULTS.md and BUILD.md
beside the guides and keeps the examples' READMEs under examples/, and the hook rewrites those links to match.
A flag table sits in its page between `<!-- flags: experiments.X -->` and `<!-- end of flags -->`, written from
the command itself (`--helpxml`) by `python docs/hooks.py`; the build fails where a table is not what the
command says today. Every `python -m experiments.X --flag...` command in the pages and README.md, outside
tables (BUILD.md's list commands that are refused), must name a command that exists and flags it defines, or
the build fails."""
from __future__ import annotations

import functools
import glob
import os
import posixpath
import re
import subprocess
import sys
import xml.etree.ElementTree as ElementTree

from mkdocs.structure.files import File

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
PAGES_FROM_ROOT = ("RESULTS.md", "BUILD.md", *sorted(glob.glob("examples/*/README.md", root_dir=ROOT)))
_FLAG_TABLE = re.compile(r"^<!-- flags: (experiments\.\w+) -->\n(.*?)^<!-- end of flags -->$", re.M | re.S)
_LINK = re.compile(r"(\]\()([^)\s#]+)((?:#[^)\s]*)?\))")
_COMMAND = re.compile(r"python -m (experiments\.[a-z_]+)\b((?:[^\n`&;|]|\\\n)*)")
_OLDER_COMMIT = re.compile(r"^```bash\ngit checkout [0-9a-f]{7,40}\b.*?^```$", re.M | re.S)
sys.path.insert(0, ROOT)  # the documentation build runs from mkdocs's script, not from the repository
from experiments.common.flag_groups import GROUPS  # noqa: E402  (after the path it is found on)


def on_files(files, config):
  """RESULTS.md, BUILD.md, the examples' READMEs and results/ (the figures) from the repository's root."""
  site, urls = config["site_dir"], config["use_directory_urls"]
  for path in (*PAGES_FROM_ROOT, *sorted(glob.glob("results/**/*.png", root_dir=ROOT, recursive=True))):
    files.append(File(path, src_dir=ROOT, dest_dir=site, use_directory_urls=urls))
  return files


def on_page_markdown(markdown: str, page, config, files) -> str:
  check_commands(markdown, page.file.src_path)
  if len(re.findall(r"^<!-- flags: ", markdown, re.M)) != len(_FLAG_TABLE.findall(markdown)):
    raise SystemExit(f"docs: {page.file.src_path}: a <!-- flags: experiments.X --> line without its "
                     "<!-- end of flags -->")
  for module, table in _FLAG_TABLE.findall(markdown):
    if table.strip() != flag_table(module):
      raise SystemExit(f"docs: {page.file.src_path}: the flag table of {module} is out of date; "
                       "`python docs/hooks.py` rewrites it")
  in_repository = page.file.src_path if page.file.src_path in PAGES_FROM_ROOT else f"docs/{page.file.src_path}"
  return _LINK.sub(lambda m: m[1] + site_link(in_repository, page.file.src_path, m[2]) + m[3], markdown)


def site_link(in_repository: str, in_site: str, target: str) -> str:
  """A relative link written in the repository file in_repository, as the same page at in_site must give it:
  RESULTS.md, BUILD.md and results/ sit at the site's root beside the guides of docs/, the examples' READMEs
  under examples/. Other links (to a page beside it, or outside the repository's pages: a URL) are left as they
  are."""
  if "://" in target or target.startswith("mailto:"):
    return target
  path = posixpath.normpath(posixpath.join(posixpath.dirname(in_repository), target))
  if path.startswith("docs/"):
    path = path[len("docs/"):]
  elif not (path in PAGES_FROM_ROOT or path.startswith("results/")):
    return target
  return posixpath.relpath(path, posixpath.dirname(in_site) or ".")


def on_pre_build(config):
  with open(os.path.join(ROOT, "README.md"), encoding="utf-8") as f:
    check_commands(f.read(), "README.md")


@functools.cache
def command_flags(module: str) -> tuple[tuple[str, str, str, str], ...]:
  """(group, name, default, help) of every flag a command defines (its own and those it adopts), read from
  `python -m module --helpxml`; SystemExit naming the module if it cannot run."""
  proc = subprocess.run([sys.executable, "-m", module, "--helpxml"], capture_output=True, text=True, cwd=ROOT,
                        env={**os.environ, "JAX_PLATFORMS": "cpu"})
  if proc.returncode != 0:
    raise SystemExit(f"docs: `python -m {module} --helpxml` failed: {proc.stderr.strip()[-500:]}")
  flags = []
  for flag in ElementTree.fromstring(proc.stdout).iter("flag"):
    source = flag.findtext("file") or ""
    if flag.findtext("key") != "yes" and source not in GROUPS:
      continue
    group = GROUPS.get(source, "the command's own")
    flags.append((group, flag.findtext("name"), flag.findtext("default") or "", flag.findtext("meaning") or ""))
  return tuple(flags)


def flag_table(module: str) -> str:
  """A Markdown table of the command's flags, its own first."""
  order = ["the command's own", *GROUPS.values()]
  rows = sorted(command_flags(module), key=lambda f: (order.index(f[0]), f[1]))
  lines = [f"Every flag of `python -m {module}` (its `--help` says the same):", "",
           "| flag | default | what it sets |", "| --- | --- | --- |"]
  for group, name, default, meaning in rows:
    meaning, _, stated = meaning.replace("\n", " ").partition(" Default: ")  # a default the help states
    shown = stated.rstrip(".") if stated else (f"`{default}`" if default else "unset")
    cells = [f"`--{name}` ({group})", shown, meaning]
    cells = [c.replace("|", "\\|").replace("<", "&lt;").replace(">", "&gt;") for c in cells]
    lines.append("| " + " | ".join(cells) + " |")
  return "\n".join(lines)


def check_commands(markdown: str, where: str) -> None:
  """SystemExit naming the page, command and flag if a command in markdown is not one, or gives a flag it
  does not define."""
  known_modules = {os.path.basename(p)[:-3] for p in glob.glob(os.path.join(ROOT, "experiments", "*.py"))}
  markdown = _OLDER_COMMIT.sub("", markdown)  # code blocks that first check out another commit run its commands
  prose = "\n".join(line for line in markdown.splitlines() if not line.startswith("|"))  # tables: refused inputs
  for match in _COMMAND.finditer(prose):
    module, rest = match.group(1), match.group(2)
    if module.split(".")[1] not in known_modules:
      raise SystemExit(f"docs: {where}: `python -m {module}` is not a command")
    if module in _NOT_ABSL:
      continue
    own, _, passed_on = rest.partition(" -- ")
    _check_flags(module, own, where)
    if module == "experiments.sweep" and passed_on:  # the flags after -- go to every run's experiments.train
      _check_flags("experiments.train", passed_on, where)


def _check_flags(module: str, text: str, where: str) -> None:
  names = {name for _, name, _, _ in command_flags(module)} | {"help", "helpfull", "verbosity"}
  for flag in re.findall(r"(?<![\w-])--([a-z_]+)", text):
    if flag not in names and not (flag.startswith("no") and flag[2:] in names):
      raise SystemExit(f"docs: {where}: `python -m {module}` has no flag --{flag}")


_NOT_ABSL = {"experiments.benchmark"}  # subcommands, each with flags of its own


def write_flag_tables() -> list[str]:
  """Rewrites every page's flag tables from the commands; returns the pages changed."""
  changed = []
  for path in sorted(glob.glob(os.path.join(ROOT, "docs", "**", "*.md"), recursive=True)):
    with open(path, encoding="utf-8") as f:
      text = f.read()
    new = _FLAG_TABLE.sub(lambda m: f"<!-- flags: {m[1]} -->\n{flag_table(m[1])}\n<!-- end of flags -->", text)
    if new != text:
      with open(path, "w", encoding="utf-8") as f:
        f.write(new)
      changed.append(os.path.relpath(path, ROOT))
  return changed


if __name__ == "__main__":
  print("\n".join(f"rewrote the flag tables of {page}" for page in write_flag_tables()) or "flag tables up to date")
