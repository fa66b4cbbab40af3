"""The one place that chooses the Mitsuba variant and finds a working libLLVM.

The variant follows the device: ``cuda_ad_rgb`` when Dr.Jit finds a CUDA device,
``llvm_ad_rgb`` otherwise. ``MITSUBA_P3_VARIANT`` (or the CLI's ``--variant``,
which sets it) forces either; forcing CUDA where there is none is refused with
the reason. No other module names a variant: renderers ask :func:`jit_backend`.

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

VARIANTS = ("llvm_ad_rgb", "cuda_ad_rgb")
VARIANT_ENV = "MITSUBA_P3_VARIANT"
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
_CHOICE: dict = {}


def choose_variant() -> tuple[str, str]:
    """``(variant, why)``: the forced variant, else CUDA when Dr.Jit sees a CUDA device, else LLVM.

    Imports Dr.Jit (after libLLVM is exported) but sets no variant."""
    forced = os.environ.get(VARIANT_ENV, "").strip()
    if forced and forced not in VARIANTS:
        raise BackendError(f"{VARIANT_ENV}={forced!r} is not a variant this project runs; "
                           f"choose one of {', '.join(VARIANTS)}")
    import drjit as dr

    has_cuda = dr.has_backend(dr.JitBackend.CUDA)
    if forced == "cuda_ad_rgb" and not has_cuda:
        raise BackendError(f"{VARIANT_ENV}=cuda_ad_rgb, but Dr.Jit finds no CUDA device (no driver "
                           "libcuda.so or no GPU); unset it to run on the CPU")
    if forced:
        return forced, f"forced by {VARIANT_ENV}"
    if has_cuda:
        return "cuda_ad_rgb", "Dr.Jit found a CUDA device"
    return "llvm_ad_rgb", "no CUDA device found; the CPU through LLVM"


def jax_on_gpu(platform: str | None = None) -> bool:
    """Whether JAX runs on a GPU (``platform``: a JAX backend's name; default: the one this process uses)."""
    if platform is None:
        import jax

        platform = jax.default_backend()
    return platform in ("gpu", "cuda", "rocm")


def follow_device(env: str, choices: tuple, on_gpu: str, elsewhere: str, error: type,
                  platform: str | None = None) -> str:
    """A choice that follows where JAX runs: ``on_gpu`` on a GPU, ``elsewhere`` otherwise; the environment
    variable ``env`` forces any of ``choices`` (another value is refused with ``error``)."""
    forced = os.environ.get(env, "").strip()
    if forced:
        if forced not in choices:
            raise error(f"{env}={forced!r}; choose one of {', '.join(choices)}")
        return forced
    return on_gpu if jax_on_gpu(platform) else elsewhere


def _cuda_available() -> bool:
    """Whether Dr.Jit finds a CUDA device; asks Dr.Jit only where the driver library loads (so a
    machine without one prints none of Dr.Jit's start-up warnings)."""
    import ctypes

    try:
        ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    import drjit as dr

    return bool(dr.has_backend(dr.JitBackend.CUDA))


def llvm_path() -> str | None:
    """The libLLVM to export before Dr.Jit starts, or None where none is needed: a machine without a
    usable libLLVM runs the CUDA variant when it is forced or Dr.Jit finds a GPU (a GPU machine need
    not carry LLVM); otherwise, and always for an explicit ``DRJIT_LIBLLVM_PATH``, :func:`find_llvm`'s
    error stands."""
    try:
        return find_llvm()[0]
    except BackendError:
        forced = os.environ.get(VARIANT_ENV, "").strip()
        if os.environ.get("DRJIT_LIBLLVM_PATH"):
            raise
        if forced == "cuda_ad_rgb" or (forced != "llvm_ad_rgb" and _cuda_available()):
            return None
        raise


def mitsuba():
    """Import Mitsuba in the variant :func:`choose_variant` picks (once) with a checked libLLVM
    and return the ``mitsuba`` module. The project's plugins register themselves when
    :mod:`mitsuba_p3.render.phong` is imported."""
    global _MI
    if _MI is not None:
        return _MI
    path = llvm_path()
    if path:
        # Read by Dr.Jit when its LLVM backend initialises, i.e. at the first LLVM array.
        os.environ["DRJIT_LIBLLVM_PATH"] = path
    try:
        import drjit as dr
        import mitsuba as mi
    except ImportError as exc:  # pragma: no cover - depends on the install
        raise BackendError(f"cannot import Mitsuba/Dr.Jit ({exc}); run `bash scripts/setup.sh`") from exc
    variant, why = choose_variant()
    if variant == "llvm_ad_rgb" and not dr.has_backend(dr.JitBackend.LLVM):
        raise BackendError(f"Dr.Jit could not initialise its LLVM backend with {path}; {INSTALL_HINT}")
    mi.set_variant(variant)
    _CHOICE.update(variant=variant, why=why)
    _MI = mi
    return mi


def jit_backend():
    """The Dr.Jit backend of the chosen variant (``dr.JitBackend.CUDA`` or ``.LLVM``)."""
    import drjit as dr

    mi = mitsuba()
    return dr.JitBackend.CUDA if mi.variant().startswith("cuda") else dr.JitBackend.LLVM


def describe() -> dict:
    """A small dict of what the backend runs on, for benchmark reports and `doctor`."""
    mi = mitsuba()
    import drjit as dr

    import platform

    out = {
        "variant": mi.variant(),
        "variant_why": _CHOICE.get("why"),
        "mitsuba": mi.MI_VERSION,
        "drjit": dr.__version__,
        "libllvm": os.environ.get("DRJIT_LIBLLVM_PATH"),
        "llvm_version": ".".join(map(str, dr.detail.llvm_version())),
        "threads": dr.thread_count(),
        "cpu_cores": os.cpu_count(),
        "cpu": platform.processor() or platform.machine(),
        "jax_compilation_cache": os.environ.get("JAX_COMPILATION_CACHE_DIR"),
        "xla_flags": os.environ.get("XLA_FLAGS", ""),     # the package's own among them (mitsuba_p3.NO_YNNPACK)
    }
    out.update(gpu())
    return out


def gpu() -> dict:
    """The GPU this process can use, as ``nvidia-smi`` names it (empty without one), and
    where JAX runs: a benchmark says where it ran."""
    import shutil
    import subprocess

    out: dict = {}
    try:
        import jax

        out["jax_backend"] = jax.default_backend()
        out["jax_devices"] = [str(d) for d in jax.devices()]
    except Exception as exc:  # pragma: no cover - depends on the install
        out["jax_backend"] = f"unavailable ({exc})"
    if shutil.which("nvidia-smi"):
        try:
            line = subprocess.run(["nvidia-smi", "--query-gpu=name,driver_version,memory.total",
                                   "--format=csv,noheader"], capture_output=True, text=True,
                                  timeout=20).stdout.strip().splitlines()
            if line:
                name, driver, memory = (v.strip() for v in line[0].split(","))
                out.update(gpu=name, gpu_driver=driver, gpu_memory=memory)
        except (OSError, subprocess.SubprocessError, ValueError):
            pass
    return out
