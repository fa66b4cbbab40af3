"""`mitsuba-p3` command line: thin subcommands over the library.

Every project error (:class:`~mitsuba_p3.errors.MitsubaP3Error`) becomes one
line on stderr and exit status 2.
"""
from __future__ import annotations

import sys

import typer

from ..errors import MitsubaP3Error
from . import scene_commands, benchmark_commands, pipeline_commands, baseline_commands  # noqa: F401, I001  (commands)
from .app import app


def main() -> None:
    try:
        app()
    except MitsubaP3Error as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
