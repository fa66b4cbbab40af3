"""The ``mitsuba-p3`` application object and what its commands share: options, progress bars."""
from __future__ import annotations

import typer

from ..errors import SceneError

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Bayesian inverse graphics for few-shot concept learning (Mitsuba 3 + JAX).")
benchmark_app = typer.Typer(no_args_is_help=True, help="Make, check and look at benchmark data sets.")
app.add_typer(benchmark_app, name="benchmark")
baseline_app = typer.Typer(no_args_is_help=True, help="Few-shot baselines: ProtoNets and MAML (Conv-4).")
app.add_typer(baseline_app, name="baseline")


def _print_version(value: bool) -> None:
    if value:
        from .. import __version__

        typer.echo(f"mitsuba-p3 {__version__}")
        raise typer.Exit()


@app.callback()
def _global_options(variant: str = typer.Option(
        None, "--variant", help="Mitsuba variant: llvm_ad_rgb (CPU) or cuda_ad_rgb (GPU); default: CUDA when "
        "Dr.Jit finds a device, else the CPU. Same as MITSUBA_P3_VARIANT."),
        version: bool = typer.Option(False, "--version", callback=_print_version, is_eager=True,
                                     help="Print the version and exit.")) -> None:
    """Bayesian inverse graphics for few-shot concept learning (Mitsuba 3 + JAX)."""
    import os

    from ..backend import VARIANT_ENV, VARIANTS

    if variant is not None:
        if variant not in VARIANTS:
            raise SceneError(f"--variant must be one of {', '.join(VARIANTS)}, got {variant!r}")
        os.environ[VARIANT_ENV] = variant  # read when Mitsuba is first imported, after this


# Options shared by the commands that take a scene and change its object.
SHAPE = typer.Option(None, help="sphere, cube or cylinder.")
COLOUR = typer.Option(None, "--color", "--colour", help="CLEVR colour name or 'r,g,b' in [0,1].")
MATERIAL = typer.Option(None, help="rubber or metal.")
SHIFT = typer.Option(None, help="'x,y' position on the floor (m).")
THETA = typer.Option(None, help="Yaw about z (degrees).")
SCALE = typer.Option(None, help="small, large, one half-extent or 'sx,sy,sz' (m).")
SETS = typer.Option(None, "--set", help="Override any <default> NAME=VALUE.")
SHADOWS = typer.Option(None, "--shadows/--no-shadows", help="Hard shadows (default: as the XML).")


def parse_resolution(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SceneError(f"--resolution must look like HxW (e.g. 120x160), got {text!r}") from None
    if height < 1 or width < 1:
        raise SceneError(f"--resolution must be positive, got {text!r}")
    return height, width


# seconds between the plain progress lines written when stderr is a file (a background run's log)
LOG_EVERY = 60.0


def progress_bar(description: str, log_every: float = LOG_EVERY):
    """A rich progress bar on stderr; returns (context manager, callback(done, total)).

    On a terminal the bar redraws itself. Written to a file (``nohup ... 2> run.log``) a live bar
    would show nothing until it stops and then leave its last frame, before any error line; there
    the bar is off and the callback writes plain lines instead, at most every ``log_every`` seconds
    and when the work is done: what, how far, for how long, and the time left at the rate so far."""
    import sys
    import time

    from rich.console import Console
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    console = Console(stderr=True)
    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), TimeRemainingColumn(), console=console, disable=not console.is_terminal)
    task = bar.add_task(description, total=None)
    # the line's clock: since the last line, and since the current description (a phase) began; the
    # rate counts from the phase's first report, since a resumed run's first report is part-way
    clock = {"line": time.monotonic(), "phase": time.monotonic(), "name": description, "first": None}

    def update(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)
        now, name = time.monotonic(), bar.tasks[0].description
        if name != clock["name"]:
            clock.update(phase=now, name=name, first=None)
        if clock["first"] is None:
            clock["first"] = (now, done)
        if console.is_terminal or not (now - clock["line"] >= log_every or (total and done >= total)):
            return
        clock["line"] = now
        spent = now - clock["phase"]
        since, done_then = clock["first"]
        rate = (done - done_then) / (now - since) if now > since else 0.0
        left = f", about {_minutes((total - done) / rate)} left" if rate > 0 and total and done < total else ""
        print(f"{name}: {done}/{total or '?'} after {_minutes(spent)}{left}", file=sys.stderr, flush=True)

    return bar, update


def _minutes(seconds: float) -> str:
    return f"{seconds / 60:.1f} min" if seconds >= 60 else f"{seconds:.0f} s"


def phase_progress_bar(description: str):
    """A progress bar whose callback(phase, done, total) also names the current phase."""
    bar, update = progress_bar(description)

    def track(phase: str, done: int, total: int) -> None:
        bar.update(bar.task_ids[0], description=phase)
        update(done, total)

    return bar, track


SAMPLER_HELP = {"chains": "MH chains per posterior, run in one batched render per step.",
                "steps": "Kept draws per chain.", "burn_in": "Burn-in steps after tuning.",
                "tune_rounds": "Tuning rounds.", "tune_steps": "Steps per tuning round."}


def sampler_option(name: str, defaults) -> typer.Option:
    """The option of one sampler setting, defaulting to ``defaults``' value (a SamplerConfig)."""
    return typer.Option(getattr(defaults, name), help=SAMPLER_HELP[name])
