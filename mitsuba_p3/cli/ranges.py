"""Every numeric option's range, in one table, checked by the parser before any work.

A number outside its range is refused in one usage line (exit status 2) naming the option and its range:
:func:`apply` gives every registered command's int and float options their ``min`` and ``max`` from
:data:`RANGES`, by the option's name, before the parser is built, and a test keeps every numeric option of
every command in the table.
"""
from __future__ import annotations

import inspect
import typing

import typer

# option name -> (lowest, highest) accepted
RANGES: dict[str, tuple] = {
    "seed": (0, 2**32 - 1), "spp": (1, 1 << 16), "channels": (1, 512), "epochs": (1, 1000),
    "material_passes": (0, 100), "global_passes": (0, 100), "learning_rate": (1e-8, 1.0),
    "light_radius": (0.0, 1.0), "light_falloff": (0.0, 10.0), "chains": (1, 1024), "steps": (1, 1_000_000),
    "burn_in": (0, 1_000_000), "tune_rounds": (0, 100), "tune_steps": (1, 100_000), "particles": (2, 1 << 16),
    "sigma": (1e-6, 10.0), "images": (1, 100_000), "draws": (1, 10_000), "jobs": (1, 256), "episodes": (1, 100_000),
    "spread_shots": (0, 100), "iterations": (1, 10_000_000), "k_shot": (1, 50), "validation_classes": (1, 1000),
    "patience": (1, 1000), "resolution": (8, 512), "theta": (-360.0, 360.0),
}


def _commands(app: typer.Typer):
    for command in app.registered_commands:
        yield command.callback
    for group in app.registered_groups:
        yield from _commands(group.typer_instance)


def numeric_options(app: typer.Typer):
    """(function, parameter name, OptionInfo) of every int or float option of every command of ``app``."""
    for function in _commands(app):
        hints = typing.get_type_hints(function)
        for name, parameter in inspect.signature(function).parameters.items():
            kind = hints.get(name)
            kind = next((a for a in typing.get_args(kind) if a is not type(None)), kind)
            if kind in (int, float) and isinstance(parameter.default, typer.models.OptionInfo):
                yield function, name, parameter.default


def apply(app: typer.Typer) -> typer.Typer:
    """Set every numeric option's ``min`` and ``max`` from :data:`RANGES` (before the parser is built)."""
    for _, name, option in numeric_options(app):
        if name in RANGES:
            option.min, option.max = RANGES[name]
    return app
