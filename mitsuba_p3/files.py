"""Atomic file writes: a killed run never leaves half a file under a final name.

Every writer in the project goes through :func:`atomic_path`: the content is
written to a hidden temporary file in the target's folder (same file system,
same suffix, so libraries that pick a format from the suffix still do), then
renamed over the target in one step (``os.replace``). On any error the
temporary file is removed and the target is left as it was.
"""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np


@contextmanager
def atomic_path(path: str | Path) -> Iterator[Path]:
    """A temporary path to write; renamed to ``path`` when the block ends without error."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, prefix=f".{path.stem}.", suffix=".tmp" + path.suffix)
    os.close(handle)
    try:
        yield Path(temporary)
        os.chmod(temporary, 0o666 & ~_UMASK)      # mkstemp makes 0600; give the file the usual mode
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)


@contextmanager
def atomic_open(path: str | Path) -> Iterator:
    """A text file (UTF-8, ``newline=""`` as the csv module wants) renamed to ``path`` when the block ends."""
    with atomic_path(path) as temporary, open(temporary, "w", newline="", encoding="utf-8") as f:
        yield f


def _read_umask() -> int:
    """The process's umask (reading it means setting it: done once, at import, not per write)."""
    mask = os.umask(0)
    os.umask(mask)
    return mask


_UMASK = _read_umask()


def atomic_write(path: str | Path, data: bytes | str) -> Path:
    """Write bytes or text (UTF-8) to ``path`` atomically."""
    with atomic_path(path) as temporary:
        temporary.write_bytes(data.encode() if isinstance(data, str) else data)
    return Path(path)


def atomic_json(path: str | Path, value, indent: int = 1) -> Path:
    """Write ``value`` as JSON atomically."""
    return atomic_write(path, json.dumps(value, indent=indent, default=str))


def atomic_npz(path: str | Path, compressed: bool = False, **arrays) -> Path:
    """Write named arrays as ``.npz`` atomically (``np.savez`` or ``np.savez_compressed``)."""
    with atomic_path(path) as temporary, open(temporary, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    return Path(path)
