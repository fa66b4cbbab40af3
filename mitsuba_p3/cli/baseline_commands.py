"""Baseline commands: meta-train ProtoNets or MAML and score them on the shared test episodes."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import numpy as np
import typer

from ..errors import MitsubaP3Error
from .app import baseline_app, progress_bar


@baseline_app.command("train")
def baseline_train(
    method: str = typer.Argument(..., help="protonets or maml."),
    dataset: Path = typer.Argument(..., help="Benchmark folder; its train split is used."),
    out: Path = typer.Option(..., "--out", help="Training folder (checkpoint, curve; resumes)."),
    resolution: int = typer.Option(56, help="Square input size: 56 or 84 as in the paper."),
    iterations: Optional[int] = typer.Option(None, help="Meta-iterations (default: protonets 2000, maml 1000)."),
    k_shot: int = typer.Option(1, help="Shots per class in the training tasks."),
    second_order: bool = typer.Option(False, help="MAML: differentiate through the inner loop."),
    seed: int = typer.Option(0),
) -> None:
    """Meta-train a baseline on a benchmark's train classes, with checkpoints and a learning curve."""
    from ..baselines.train import DEFAULT_ITERATIONS, TrainConfig, train_baseline

    if resolution not in (56, 84):
        raise MitsubaP3Error("--resolution must be 56 or 84 (the paper's inputs)")
    config = TrainConfig(method=method, resolution=resolution, k_shot=k_shot, second_order=second_order, seed=seed,
                         iterations=iterations or DEFAULT_ITERATIONS.get(method, 1000))
    bar, update = progress_bar(f"{method} {resolution}")
    with bar:
        state = train_baseline(dataset, out, config, progress=update)
    last = state.curve[-100:]
    typer.echo(json.dumps({"out": str(out), "iterations": state.iteration,
                           "recent_loss": round(float(np.mean([c[1] for c in last])), 4),
                           "recent_query_accuracy": round(float(np.mean([c[2] for c in last])), 4),
                           "learning_curve": str(out / "learning_curve.png")}, indent=2))


@baseline_app.command("evaluate")
def baseline_evaluate(
    trained: Path = typer.Argument(..., help="Training folder (mitsuba-p3 baseline train)."),
    dataset: Path = typer.Argument(..., help="Benchmark folder; its test episodes are used."),
    out: Path = typer.Option(..., "--out", help="Evaluation run folder (results go to baselines/)."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting (same as evaluate)."),
) -> None:
    """Accuracy on the same test episodes as P3/NP3; the evaluation tables pick it up."""
    from ..baselines.train import evaluate_baseline

    bar, update = progress_bar("episodes")
    with bar:
        result = evaluate_baseline(trained, dataset, out, episodes, progress=update)
    typer.echo(json.dumps({result["model"]: {k: round(100 * v["mean"], 1) for k, v in result["accuracy"].items()}},
                          indent=2))
