"""`mitsuba-p3` command line: thin subcommands over the library.

Every project error (:class:`~mitsuba_p3.errors.MitsubaP3Error`) becomes one
line on stderr and exit status 2; a number outside its option's range (:mod:`.ranges`) is refused by the
parser the same way.
"""
from __future__ import annotations

import sys

import typer

from ..errors import MitsubaP3Error
from . import scene_commands, benchmark_commands, pipeline_commands, baseline_commands  # noqa: F401, I001  (commands)
from .app import app
from .ranges import apply

apply(app)


def main() -> None:
    try:                               # typer 0.29 carries its own copy of click
        from typer._click import exceptions
    except ImportError:                # pragma: no cover - older typer on click itself
        from click import exceptions

    try:
        code = app(standalone_mode=False)
    except MitsubaP3Error as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)
    except exceptions.NoArgsIsHelpError as exc:
        typer.echo(exc.ctx.get_help())
        sys.exit(0)
    except exceptions.UsageError as exc:          # a bad option or value, refused by the parser: one line too
        where = exc.ctx.command_path if exc.ctx else "mitsuba-p3"
        typer.echo(f"error: {exc.format_message()} (see {where} --help)", err=True)
        sys.exit(2)
    except exceptions.ClickException as exc:
        typer.echo(f"error: {exc.format_message()}", err=True)
        sys.exit(exc.exit_code)
    sys.exit(code if isinstance(code, int) else 0)
