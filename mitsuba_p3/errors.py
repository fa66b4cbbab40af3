"""Project exceptions: every user-facing failure is one of these, with a message
that names the file or value at fault and how to fix it."""


class MitsubaP3Error(Exception):
    """Base class; the CLI prints its message as one line and exits non-zero."""


class BackendError(MitsubaP3Error):
    """No usable Dr.Jit/LLVM backend (missing or known-broken libLLVM)."""


class SceneError(MitsubaP3Error):
    """A scene description (XML or parameters) is malformed or out of range."""


class ImageError(MitsubaP3Error):
    """An image file is missing, unreadable or not an RGB picture."""


class BenchmarkError(MitsubaP3Error):
    """A benchmark request or folder does not follow the protocol."""


class DatasetError(BenchmarkError):
    """A data-set folder is incomplete or inconsistent; the message lists every problem."""


class FitError(MitsubaP3Error):
    """The training stage cannot run on this input."""


class InferenceError(MitsubaP3Error):
    """An observation or request cannot be used for inference."""


class EvaluationError(MitsubaP3Error):
    """A run folder or its settings are unusable."""


class BaselineError(MitsubaP3Error):
    """Bad baseline settings or an unusable training folder."""


class ConfigError(MitsubaP3Error):
    """A configuration value is out of range; raised before any work starts."""


def check_counts(config, least: dict[str, int], what: str = "") -> None:
    """Raise :class:`ConfigError` unless each named field of ``config`` is a whole number >= its least value.

    The message names the field as its command-line flag (``burn_in`` -> ``burn-in``)."""
    for name, minimum in least.items():
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
            raise ConfigError(f"{what}{name.replace('_', '-')} must be a whole number >= {minimum}; got {value!r}")


def check_positive(config, names: tuple[str, ...], what: str = "") -> None:
    """Raise :class:`ConfigError` unless each named field of ``config`` is a finite number > 0."""
    import math

    for name in names:
        value = getattr(config, name)
        if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value <= 0:
            raise ConfigError(f"{what}{name.replace('_', '-')} must be a positive number; got {value!r}")
