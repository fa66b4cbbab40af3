"""libLLVM discovery: a usable library is found, and unusable ones fail with the fix."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mitsuba_p3 import backend
from mitsuba_p3.errors import BackendError


@pytest.mark.parametrize("name, version", [
    ("libLLVM-19.so", 19), ("libLLVM.so.19.1", 19), ("libLLVM-15.so.1", 15), ("libLLVM-14.0.6.so.1", 14),
    ("libLLVM.so", None), ("libc.so.6", None),
])
def test_version_from_file_name(name, version):
    assert backend.llvm_version_of(f"/usr/lib/{name}") == version


def test_finds_a_usable_llvm_here(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    path, version = backend.find_llvm()
    assert os.path.isfile(path) and version >= backend.MIN_LLVM_VERSION


def test_only_broken_versions_is_a_clear_error(monkeypatch, tmp_path):
    (tmp_path / "libLLVM-15.so").write_bytes(b"")
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(backend, "_SEARCH_GLOBS", (str(tmp_path / "libLLVM*.so*"),))
    with pytest.raises(BackendError, match="found only: .*libLLVM-15.so.*libllvm19"):
        backend.find_llvm()


@pytest.mark.parametrize("name, message", [("libLLVM-15.so", "LLVM 15"), ("missing.so", "does not exist")])
def test_bad_explicit_path(monkeypatch, tmp_path, name, message):
    if name != "missing.so":
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / name))
    with pytest.raises(BackendError, match=message):
        backend.find_llvm()


def test_cli_reports_a_broken_llvm_in_one_line(tmp_path):
    """No abort: a known-broken libLLVM is refused before Dr.Jit ever loads it."""
    fake = tmp_path / "libLLVM-15.so"
    fake.write_bytes(b"")
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": str(fake)}
    done = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "doctor"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "libllvm19" in lines[0]
