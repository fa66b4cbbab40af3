"""mitsuba-p3: Bayesian inverse graphics for few-shot concept learning.

    >>> import mitsuba_p3 as p3
    >>> model = p3.load_model("out/model-small")                        # doctest: +SKIP
    >>> post = p3.infer_image(model, "image.png")                       # doctest: +SKIP
    >>> post.shape_probabilities, post.estimate()["shift"]              # doctest: +SKIP

The public names (:data:`__all__`) come from :mod:`mitsuba_p3.api` and are imported on first use, so
``import mitsuba_p3`` stays light. Scenes (:mod:`mitsuba_p3.scene`) are rendered by the Phong renderers
of :mod:`mitsuba_p3.render`; Mitsuba is imported lazily through :mod:`mitsuba_p3.backend`, which picks a
working libLLVM first.
"""
import os as _os

__version__ = "0.1.0"
__all__ = ["load_model", "load_image", "infer_image", "sampler_config", "Posterior", "__version__"]


def __getattr__(name: str):
    if name == "Posterior":
        from .infer.posterior import Posterior

        return Posterior
    if name in __all__:
        from . import api

        return getattr(api, name)
    raise AttributeError(f"module 'mitsuba_p3' has no attribute {name!r}")


def _jax_compilation_cache() -> str | None:
    """Where JAX keeps compiled programs between processes: ``MITSUBA_P3_JAX_CACHE`` (``off`` for none),
    else ``$XDG_CACHE_HOME/mitsuba-p3/jax`` (``~/.cache``). The JAX tracer's programs then compile once
    per machine and model, not once per command (JAX does not cache programs with host callbacks, so
    the Mitsuba renderer's compile per process); a cache JAX was already told of is left alone."""
    chosen = _os.environ.get("MITSUBA_P3_JAX_CACHE")
    if chosen is not None and chosen.strip().lower() in ("", "off", "none", "0", "false"):
        return None
    default = _os.path.join(_os.environ.get("XDG_CACHE_HOME") or _os.path.join("~", ".cache"), "mitsuba-p3", "jax")
    return _os.path.expanduser(chosen or default)


# The XLA flag that keeps XLA's CPU backend from handing fusions to YNNPACK (jaxlib 0.8.1 and later).
NO_YNNPACK = "--xla_cpu_experimental_ynn_fusion_type="


def _xla_flags(flags: str, jaxlib_version: str | None) -> str:
    """``XLA_FLAGS`` for this process: ``flags`` with :data:`NO_YNNPACK` added where jaxlib knows it.

    From jaxlib 0.8.1 on, XLA's CPU backend hands small fused element-wise ops, reductions and dots
    to YNNPACK. A posterior's are small (a 3 x 3 block or three colours per particle, over the SMC's
    particles) and take less time in XLA's own loops: the same arithmetic up to float32 rounding. Flags that already name
    the YNNPACK fusions are left as they are, and ``MITSUBA_P3_YNNPACK=on`` leaves XLA's default.
    An older jaxlib has no such flag, and XLA stops a process on a flag it does not know, so none is
    added there."""
    import re

    if "ynn_fusion_type" in flags or _os.environ.get("MITSUBA_P3_YNNPACK", "").strip().lower() in ("on", "1", "true"):
        return flags
    parts = re.findall(r"\d+", jaxlib_version or "")[:3]
    if len(parts) < 3:
        return flags
    version = tuple(int(part) for part in parts)
    return f"{flags} {NO_YNNPACK}".strip() if version >= (0, 8, 1) else flags


def _jaxlib_version() -> str | None:
    from importlib import metadata

    try:
        return metadata.version("jaxlib")
    except metadata.PackageNotFoundError:
        return None


# read by JAX when it is first imported (every module imports it lazily, after this) and by XLA when
# its backend starts: a process that ran JAX before importing this package keeps XLA's settings
if _jax_compilation_cache() is not None:
    _os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _jax_compilation_cache())
_flags = _xla_flags(_os.environ.get("XLA_FLAGS", ""), _jaxlib_version())
if _flags:
    _os.environ["XLA_FLAGS"] = _flags
