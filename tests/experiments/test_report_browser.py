"""A run's report.html in a real browser: headless Chromium (Debian's `chromium` package) renders it, with
no console message and nothing fetched, to a screenshot of the window's size that is not blank."""
import pathlib
import shutil
import struct
import subprocess
import sys
import zlib

import pytest

WAREHOUSE = pathlib.Path(__file__).resolve().parents[2] / "examples" / "warehouse"
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
WIDTH, HEIGHT = 1280, 2400


def _png_size_and_colours(data: bytes) -> tuple[tuple[int, int], int]:
  """(width, height) of a PNG and how many distinct bytes its pixel data holds (1 for a blank page)."""
  width, height = struct.unpack(">II", data[16:24])
  chunks, at = [], 8
  while at < len(data):
    length, kind = struct.unpack(">I4s", data[at:at + 8])
    if kind == b"IDAT":
      chunks.append(data[at + 8:at + 8 + length])
    at += 12 + length
  return (width, height), len(set(zlib.decompress(b"".join(chunks))))


@pytest.mark.slow
@pytest.mark.skipif(CHROMIUM is None, reason="needs Debian's chromium (apt-get install chromium)")
def test_report_renders_in_headless_chromium_without_console_errors(tmp_path):
  workdir = tmp_path / "fit"
  proc = subprocess.run([sys.executable, "-m", "experiments.fit", f"--demos={WAREHOUSE / 'train.jsonl'}",
                         f"--hierarchy={WAREHOUSE / 'warehouse.json'}", f"--workdir={workdir}", "--iterations=100",
                         "--eval_every=50", "--hidden=16"], capture_output=True, text=True, timeout=600)
  assert proc.returncode == 0, proc.stderr
  report = workdir / "report.html"
  screenshot = tmp_path / "report.png"
  browser = subprocess.run(
      [CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
       "--disable-background-networking", "--disable-component-update", "--disable-sync",
       f"--user-data-dir={tmp_path / 'profile'}", f"--window-size={WIDTH},{HEIGHT}", "--enable-logging=stderr",
       "--v=0", f"--screenshot={screenshot}", report.as_uri()], capture_output=True, text=True, timeout=120)
  assert browser.returncode == 0, browser.stderr[-3000:]
  console = [line for line in browser.stderr.splitlines() if ":CONSOLE" in line]
  assert console == [], console
  size, colours = _png_size_and_colours(screenshot.read_bytes())
  assert size == (WIDTH, HEIGHT) and colours > 10
  html = report.read_text()
  assert "<script" not in html and " src=" not in html and "<link" not in html  # nothing to fetch or run
