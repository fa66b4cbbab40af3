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


def progress_bar(description: str):
    """A rich progress bar on stderr; returns (context manager, callback(done, total))."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), TimeRemainingColumn(), transient=False)
    task = bar.add_task(description, total=None)

    def update(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)

    return bar, update


def phase_progress_bar(description: str):
    """A progress bar whose callback(phase, done, total) also names the current phase."""
    bar, _ = progress_bar(description)

    def track(phase: str, done: int, total: int) -> None:
        bar.update(bar.task_ids[0], description=phase, completed=done, total=total)

    return bar, track


SAMPLER_HELP = {"chains": "MH chains per posterior, run in one batched render per step.",
                "steps": "Kept draws per chain.", "burn_in": "Burn-in steps after tuning.",
                "tune_rounds": "Tuning rounds.", "tune_steps": "Steps per tuning round."}


def sampler_option(name: str, defaults) -> typer.Option:
    """The option of one sampler setting, defaulting to ``defaults``' value (a SamplerConfig)."""
    return typer.Option(getattr(defaults, name), help=SAMPLER_HELP[name])
