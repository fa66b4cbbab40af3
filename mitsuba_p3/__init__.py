"""mitsuba-p3: Bayesian inverse graphics for few-shot concept learning.

Scenes (:mod:`mitsuba_p3.scene`) are rendered by the Phong renderers of
:mod:`mitsuba_p3.render`; Mitsuba is imported lazily through
:mod:`mitsuba_p3.backend`, which picks a working libLLVM first.
"""
import os as _os

__version__ = "0.1.0"


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


# read by JAX when it is first imported (every module imports it lazily, after this)
if _jax_compilation_cache() is not None:
    _os.environ.setdefault("JAX_COMPILATION_CACHE_DIR", _jax_compilation_cache())
