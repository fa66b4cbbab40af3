"""The one place that chooses the Mitsuba variant and finds a working libLLVM.

Dr.Jit's LLVM backend loads ``libLLVM`` at run time. Debian 12's LLVM 15 makes
it abort ("Cannot select ... fmaximum") and LLVM 14 is not found, so we pick the
newest usable library ourselves, export it as ``DRJIT_LIBLLVM_PATH`` *before*
Dr.Jit initialises, and raise :class:`BackendError` with the fix when there is
none -- never an abort.
"""
from __future__ import annotations

import glob
import os
import re
from pathlib import Path

from .errors import BackendError

VARIANT = "llvm_ad_rgb"
MIN_LLVM_VERSION = 16  # 15 aborts inside Dr.Jit 1.5; 14 is not loadable.
INSTALL_HINT = ("install Debian's libllvm19 (`apt-get install -y libllvm19`, or run "
                "`bash scripts/setup.sh`), or point DRJIT_LIBLLVM_PATH at libLLVM >= "
                f"{MIN_LLVM_VERSION}")

_SEARCH_GLOBS = (
    "/usr/lib/x86_64-linux-gnu/libLLVM*.so*",
    "/usr/lib/aarch64-linux-gnu/libLLVM*.so*",
    "/usr/lib/llvm-*/lib/libLLVM*.so*",
    "/usr/lib64/libLLVM*.so*",
    "/usr/local/lib/libLLVM*.so*",
    "/opt/homebrew/opt/llvm/lib/libLLVM*.dylib",
)


def llvm_version_of(path: str | os.PathLike) -> int | None:
    """Major LLVM version read from a library file name, e.g. ``libLLVM-19.so`` -> 19."""
    name = Path(path).name
    match = re.match(r"libLLVM[-.]?(?:so\.)?(\d+)", name)
    return int(match.group(1)) if match else None


def find_llvm() -> tuple[str, int]:
    """Return ``(path, major_version)`` of the newest usable libLLVM.

    An explicit ``DRJIT_LIBLLVM_PATH`` wins, but is still checked: a missing file
    or a known-broken version raises :class:`BackendError` instead of aborting later.
    """
    explicit = os.environ.get("DRJIT_LIBLLVM_PATH")
    if explicit:
        if not Path(explicit).is_file():
            raise BackendError(f"DRJIT_LIBLLVM_PATH={explicit} does not exist; {INSTALL_HINT}")
        version = llvm_version_of(explicit)
        if version is not None and version < MIN_LLVM_VERSION:
            raise BackendError(f"DRJIT_LIBLLVM_PATH={explicit} is LLVM {version}, which Dr.Jit "
                               f"cannot use; {INSTALL_HINT}")
        return explicit, version or 0

    candidates: dict[int, str] = {}
    for pattern in _SEARCH_GLOBS:
        for path in sorted(glob.glob(pattern)):
            version = llvm_version_of(path)
            if version is not None and version >= MIN_LLVM_VERSION and Path(path).is_file():
                candidates.setdefault(version, path)
    if not candidates:
        found = sorted({p for g in _SEARCH_GLOBS for p in glob.glob(g)})
        seen = f" (found only: {', '.join(found)})" if found else ""
        raise BackendError(f"no usable libLLVM >= {MIN_LLVM_VERSION} for Dr.Jit{seen}; {INSTALL_HINT}")
    best = max(candidates)
    return candidates[best], best


_MI = None


def mitsuba():
    """Import Mitsuba in the ``llvm_ad_rgb`` variant (once) with a checked libLLVM and return
    the ``mitsuba`` module. The project's plugins register themselves when
    :mod:`mitsuba_p3.render.phong` is imported."""
    global _MI
    if _MI is not None:
        return _MI
    path, _ = find_llvm()
    # Read by Dr.Jit when its LLVM backend initialises, i.e. at the first LLVM array.
    os.environ["DRJIT_LIBLLVM_PATH"] = path
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise BackendError(f"cannot import Mitsuba/Dr.Jit ({exc}); run `bash scripts/setup.sh`") from exc
    if not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(f"Dr.Jit could not initialise its LLVM backend with {path}; {INSTALL_HINT}")
    mi.set_variant(VARIANT)
    _MI = mi
    return mi


def describe() -> dict:
    """A small dict of what the backend runs on, for benchmark reports and `doctor`."""
    mi = mitsuba()
    import drjit as dr

    return {
        "variant": mi.variant(),
        "mitsuba": mi.MI_VERSION,
        "drjit": dr.__version__,
        "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH"),
        "llvm_version": ".".join(map(str, dr.detail.llvm_version())),
        "threads": dr.thread_count(),
    }
