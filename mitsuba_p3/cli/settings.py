"""Every field of the sampler configs from the command line: ``--set smc.islands=3`` and ``--config FILE``.

``infer``, ``evaluate`` and ``reproduce`` build their sampler from their named options
(``--sampler``, ``--particles``, ``--chains`` ...); :func:`apply_settings` then overrides any
field of the chosen config, so every field of :class:`~mitsuba_p3.infer.smc.SMCConfig` (``smc.``)
and :class:`~mitsuba_p3.infer.mcmc.SamplerConfig` (``mh.``) is reachable without an option of its
own. ``--config FILE`` is a JSON object ``{"smc": {...}, "mh": {...}}`` applied first; ``--set``
pairs after it, in order. A value is read by the field's type (a number, ``true``/``false``, a
window ``56x72`` or ``none``); an unknown field, a malformed value or a setting for the sampler not
chosen is refused in one line, and the config's own checks then run, so what a run folder records
(``run.json``) is exactly the config used.
"""
from __future__ import annotations

import dataclasses
import json
import typing
from pathlib import Path

from ..errors import ConfigError

PREFIXES = {"smc": "SMCConfig", "mh": "SamplerConfig"}
SET_HELP = ("Any sampler setting, as SAMPLER.FIELD=VALUE (repeatable): e.g. smc.islands=3, smc.window=none, "
            "mh.jump_probability=0.1; SAMPLER is smc or mh (the one --sampler chose).")
CONFIG_HELP = "A JSON file {\"smc\": {FIELD: VALUE}, \"mh\": {...}} of sampler settings, applied before --set."


def _parse(name: str, text: str, kind) -> object:
    """``text`` as a value of the field's type ``kind``."""
    origin, args = typing.get_origin(kind), typing.get_args(kind)
    optional = type(None) in args
    if optional and text.strip().lower() in ("none", "null"):
        return None
    if optional:
        kind = next(a for a in args if a is not type(None))
        origin = typing.get_origin(kind)
    if kind is bool:
        if text.lower() not in ("true", "false", "1", "0", "yes", "no"):
            raise ConfigError(f"{name} takes true or false; got {text!r}")
        return text.lower() in ("true", "1", "yes")
    if kind is int:
        try:
            return int(text)
        except ValueError:
            raise ConfigError(f"{name} takes a whole number; got {text!r}") from None
    if kind is float:
        try:
            return float(text)
        except ValueError:
            raise ConfigError(f"{name} takes a number; got {text!r}") from None
    if kind is tuple or origin is tuple:
        try:
            return tuple(int(v) for v in text.lower().replace(",", "x").split("x"))
        except ValueError:
            raise ConfigError(f"{name} takes HxW (e.g. 56x72) or none; got {text!r}") from None
    if kind is str:
        return text
    raise ConfigError(f"{name} cannot be set from the command line")


def _as_text(value) -> str:
    """A JSON value as the text ``--set`` would give: 3, true, none, 56x72."""
    if value is None:
        return "none"
    if isinstance(value, bool):
        return "true" if value else "false"
    if isinstance(value, list):
        return "x".join(str(v) for v in value)
    return str(value)


def _field_types(config) -> dict:
    hints = typing.get_type_hints(type(config))
    return {f.name: hints[f.name] for f in dataclasses.fields(config)}


def apply_settings(config, settings: list[str] | None = None, config_file: Path | None = None):
    """``config`` (an SMC or MH sampler config) with the fields ``config_file`` and ``settings`` name
    (see the module docstring), checked by the config's own validation."""
    from ..infer.mcmc import SamplerConfig
    from ..infer.smc import SMCConfig

    chosen = "smc" if isinstance(config, SMCConfig) else "mh"
    assert isinstance(config, (SMCConfig, SamplerConfig))
    types = _field_types(config)
    changes: dict = {}

    def unknown(name: str) -> ConfigError:
        return ConfigError(f"{chosen} has no setting {name!r}; it has {', '.join(types)}")

    if config_file is not None:
        try:
            given = json.loads(Path(config_file).read_text())
        except (OSError, json.JSONDecodeError) as exc:
            raise ConfigError(f"{config_file}: not a readable JSON settings file ({exc})") from None
        if not isinstance(given, dict) or set(given) - set(PREFIXES):
            raise ConfigError(f"{config_file}: expected {{\"smc\": {{...}}, \"mh\": {{...}}}}")
        for name, value in (given.get(chosen) or {}).items():
            if name not in types:
                raise unknown(name)
            changes[name] = _parse(f"{chosen}.{name}", _as_text(value), types[name])
    for setting in settings or []:
        key, sep, text = setting.partition("=")
        prefix, dot, name = key.strip().partition(".")
        if not sep or not dot or prefix not in PREFIXES:
            raise ConfigError(f"--set takes SAMPLER.FIELD=VALUE with SAMPLER smc or mh; got {setting!r}")
        if prefix != chosen:
            raise ConfigError(f"--set {setting}: the sampler is {chosen}, not {prefix} "
                              f"(choose it with --sampler {prefix})")
        if name not in types:
            raise unknown(name)
        changes[name] = _parse(key, text.strip(), types[name])
    try:
        return dataclasses.replace(config, **changes)
    except TypeError as exc:
        raise ConfigError(f"sampler settings: {exc}") from None
