"""Atomic file writes, and output folders that are the command's own.

A killed run never leaves half a file under a final name.

Every writer in the project goes through :func:`atomic_path`: the content is
written to a hidden temporary file in the target's folder (same file system,
same suffix, so libraries that pick a format from the suffix still do), then
renamed over the target in one step (``os.replace``). On any error the
temporary file is removed and the target is left as it was.

:func:`claim_output_folder` is the one rule for a command's output folder: it
is created, or it is empty, or it holds that command's own earlier output
(resumed or extended). A data set, a fitted model or anything else is refused
before any work starts, so no command overwrites what it did not make.
"""
from __future__ import annotations

import json
import os
import tempfile
from contextlib import contextmanager
from pathlib import Path
from typing import Iterator

import numpy as np

from .errors import MitsubaP3Error

# what marks a folder as a data set or a fitted model: never an output folder of another command
FOLDER_KINDS = {"labels.json": "a benchmark data set", "model.json": "a fitted model", "run.json": "an evaluation run",
                "posterior.nc": "a posterior (mitsuba-p3 infer)"}


# the folders no command writes inside unless it made them: their files are some run's input
PROTECTED_MARKERS = {"labels.json": "a benchmark data set", "model.json": "a fitted model"}


def refuse_inside_protected(path: str | Path, command: str) -> None:
    """The one rule for outputs: refuse ``path`` when a folder above it (links followed) is a data set
    or a fitted model, so that no command writes inside a folder it did not make. ``path`` itself is
    the caller's to check (a data set may be resumed by ``benchmark generate``, a model by ``fit``)."""
    real = Path(os.path.realpath(Path(path).expanduser()))
    for folder in real.parents:
        for marker, kind in PROTECTED_MARKERS.items():
            if (folder / marker).is_file():
                raise MitsubaP3Error(f"{path} lies inside {kind} ({folder}); {command} never writes into one: "
                                     "give an output outside it")


def refuse_protected_folder(path: str | Path, command: str) -> None:
    """:func:`refuse_inside_protected`, and refuse ``path`` itself being a data set or a fitted model:
    for commands whose output folder is neither (training runs, tables)."""
    refuse_inside_protected(path, command)
    for marker, kind in PROTECTED_MARKERS.items():
        if (Path(path) / marker).is_file():
            raise MitsubaP3Error(f"{path} is {kind}; {command} never writes into one: give another output folder")


def claim_output_folder(path: str | Path, own: str | tuple, command: str) -> Path:
    """Create ``path`` for ``command``'s output, or accept it if it is empty or holds one of ``own``
    (the files that command writes, e.g. ``model.json``); refuse a file, another kind of folder, or a
    folder of other files, with one line naming the fix. Nothing is written on refusal."""
    owns = (own,) if isinstance(own, str) else tuple(own)
    path = Path(path)
    refuse_inside_protected(path, command)
    if path.exists() and not path.is_dir():
        raise MitsubaP3Error(f"{path} is a file; {command} writes a folder: give a new folder name")
    if path.is_dir():
        entries = [e.name for e in path.iterdir() if e.name != ".lock"]
        for marker, kind in FOLDER_KINDS.items():
            if marker not in owns and marker in entries:
                raise MitsubaP3Error(f"{path} holds {kind} ({marker}); {command} will not write into it: "
                                     "give another --out folder")
        if entries and not set(entries) & set(owns):
            raise MitsubaP3Error(f"{path} is not empty and holds no {owns[0]}: it is not {command}'s output; "
                                 "give a new or empty folder")
    path.mkdir(parents=True, exist_ok=True)
    return path


def file_digest(path: str | Path) -> str:
    """SHA-256 of a file's bytes ("missing" for no file): what a record keeps to notice a file rewritten
    in place."""
    import hashlib

    path = Path(path)
    return hashlib.sha256(path.read_bytes()).hexdigest() if path.is_file() else "missing"


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


def finite_json(value):
    """``value`` with every non-finite float (NaN, infinity) as None: JSON has no NaN, and a bare
    ``NaN`` in a file makes it unreadable to strict parsers."""
    if isinstance(value, float):
        return value if np.isfinite(value) else None
    if isinstance(value, np.floating):
        return float(value) if np.isfinite(value) else None
    if isinstance(value, dict):
        return {key: finite_json(item) for key, item in value.items()}
    if isinstance(value, (list, tuple)):
        return [finite_json(item) for item in value]
    return value


def atomic_json(path: str | Path, value, indent: int = 1) -> Path:
    """Write ``value`` as strict JSON atomically (non-finite numbers as null)."""
    return atomic_write(path, json.dumps(finite_json(value), indent=indent, default=str, allow_nan=False))


def atomic_npz(path: str | Path, compressed: bool = False, **arrays) -> Path:
    """Write named arrays as ``.npz`` atomically (``np.savez`` or ``np.savez_compressed``)."""
    with atomic_path(path) as temporary, open(temporary, "wb") as f:
        (np.savez_compressed if compressed else np.savez)(f, **arrays)
    return Path(path)


@contextmanager
def folder_lock(path: str | Path, command: str, shared: bool = False) -> Iterator[None]:
    """Hold ``path/.lock`` (an advisory ``flock``) for a block: a second run into the same folder is
    refused at once instead of computing everything twice. The kernel drops the lock when its
    process dies, so a killed run never leaves a stale lock.

    ``shared``: a reader's lock (``infer`` on a model folder): many readers at once, but none while a
    writer (``fit``) holds the folder, and no writer while one reads. A folder the reader cannot
    write is not locked: no one else can write it either."""
    import fcntl

    path = Path(path)
    if not shared:
        path.mkdir(parents=True, exist_ok=True)
    try:
        handle = open(path / ".lock", "r" if shared and not os.access(path, os.W_OK) else "a+")
    except OSError:
        if not shared:
            raise
        yield
        return
    try:
        try:
            fcntl.flock(handle, (fcntl.LOCK_SH if shared else fcntl.LOCK_EX) | fcntl.LOCK_NB)
        except BlockingIOError:
            handle.seek(0)
            owner = handle.read().strip() or "another process"
            doing = "being written by" if shared else "in use by"
            raise MitsubaP3Error(f"{command}: {path} is {doing} another run (pid {owner}); wait for it to "
                                 f"finish{'' if shared else ' or give another --out folder'}") from None
        if not shared:
            handle.seek(0)
            handle.truncate()
            handle.write(str(os.getpid()))
            handle.flush()
        yield
    finally:
        handle.close()
