"""Atomic writes: the whole file or nothing, with the usual file mode."""
from __future__ import annotations

import os

import pytest

from mitsuba_p3.files import atomic_json, atomic_path, atomic_write


def test_atomic_write_replaces_whole_files_with_the_usual_mode(tmp_path):
    target = atomic_write(tmp_path / "sub" / "a.txt", "first")
    atomic_json(target, {"second": 2})
    assert target.read_text().strip().startswith("{") and "second" in target.read_text()
    mask = os.umask(0)
    os.umask(mask)
    assert os.stat(target).st_mode & 0o777 == 0o666 & ~mask


def test_a_failed_write_leaves_the_old_file_and_no_temporary(tmp_path):
    target = atomic_write(tmp_path / "a.txt", "old")
    with pytest.raises(RuntimeError):
        with atomic_path(target) as temporary:
            temporary.write_text("half")
            raise RuntimeError("killed")
    assert target.read_text() == "old" and sorted(p.name for p in tmp_path.iterdir()) == ["a.txt"]
