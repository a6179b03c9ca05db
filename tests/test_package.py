"""Packaging and provenance: the version, the versions results.json records, and how files are written."""
import importlib.metadata
import os
import stat

import jax
import pytest

import php_jax
from php_jax.data import files
from php_jax.training import provenance


def test_version_is_the_installed_metadata_version():
  assert php_jax.__version__ == importlib.metadata.version("php_jax")


def test_environment_versions_name_the_code_and_the_device():
  versions = provenance.environment_versions()
  assert versions["php_jax"] == php_jax.__version__ and versions["jax"] == jax.__version__
  for name in ("flax", "optax", "jaxlib"):
    assert versions[name] == importlib.metadata.version(name)
  device = jax.devices()[0]
  assert (versions["platform"], versions["device_kind"]) == (device.platform, device.device_kind)
  assert (versions["devices"], versions["processes"]) == (jax.device_count(), 1)


@pytest.fixture
def set_umask():
  """Sets the process umask for one test; restores it after."""
  previous = os.umask(0o022)
  yield os.umask
  os.umask(previous)


@pytest.mark.parametrize("mask, mode", [(0o022, 0o644), (0o077, 0o600), (0o002, 0o664)],
                         ids=["umask022", "umask077", "umask002"])
def test_write_atomically_gives_the_mode_open_would(tmp_path, set_umask, mask, mode):
  set_umask(mask)
  path = tmp_path / "sub" / "results.json"
  files.write_atomically(str(path), b"{}")
  assert path.read_bytes() == b"{}" and stat.S_IMODE(path.stat().st_mode) == mode
  files.write_atomically(str(path), b"[]")  # replacing an existing file
  assert path.read_bytes() == b"[]" and stat.S_IMODE(path.stat().st_mode) == mode
  assert os.listdir(path.parent) == ["results.json"]


@pytest.mark.parametrize("exists", [True, False], ids=["to_a_file", "dangling"])
def test_write_atomically_through_a_symbolic_link_writes_the_file_it_names(tmp_path, exists):
  (tmp_path / "real").mkdir()
  target, link = tmp_path / "real" / "out.jsonl", tmp_path / "link.jsonl"
  if exists:
    target.write_bytes(b"old")
  link.symlink_to(target)
  files.write_atomically(str(link), b"new")
  assert link.is_symlink() and target.read_bytes() == b"new" and os.listdir(tmp_path / "real") == ["out.jsonl"]


def test_write_atomically_removes_its_temporary_file_when_the_write_fails(tmp_path):
  path = tmp_path / "results.json"
  path.write_bytes(b"old")
  with pytest.raises(TypeError):
    files.write_atomically(str(path), object())  # not bytes: the write itself raises
  assert os.listdir(tmp_path) == ["results.json"] and path.read_bytes() == b"old"


def test_a_failed_write_removes_the_folders_it_made_for_its_file(tmp_path):
  (tmp_path / "kept").mkdir()

  def failing():
    yield b"first line\n"
    raise ValueError("the recording failed")

  with pytest.raises(ValueError, match="the recording failed"):
    files.write_streamed(str(tmp_path / "new" / "sub" / "o.jsonl"), failing())
  with pytest.raises(TypeError):
    files.write_atomically(str(tmp_path / "kept" / "new" / "o.json"), object())
  assert sorted(os.listdir(tmp_path)) == ["kept"] and os.listdir(tmp_path / "kept") == []


@pytest.mark.parametrize("error", [OSError("disk full"), KeyboardInterrupt()])
def test_write_atomically_removes_its_temporary_file_when_the_rename_fails(tmp_path, monkeypatch, error):
  def fail(src, dst):
    assert os.path.exists(src)  # the data was written to the temporary file
    raise error
  monkeypatch.setattr(os, "replace", fail)
  with pytest.raises(type(error)):
    files.write_atomically(str(tmp_path / "results.json"), b"{}")
  assert os.listdir(tmp_path) == []
