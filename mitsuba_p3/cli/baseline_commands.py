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
    out: Path = typer.Option(..., "-o", "--out", help="Training folder (checkpoint, curve; resumes)."),
    resolution: int = typer.Option(56, help="Square input size: 56 or 84 as in the paper."),
    iterations: Optional[int] = typer.Option(None, help="Cap on meta-iterations (default 20000); training "
                                             "stops earlier when the validation accuracy stops improving."),
    k_shot: int = typer.Option(1, help="Shots per class in the training tasks."),
    second_order: bool = typer.Option(False, help="MAML: differentiate through the inner loop."),
    validation_classes: Optional[int] = typer.Option(None, help="Train classes held out for early stopping "
                                                     "(0: none; default 10, at most a third)."),
    patience: Optional[int] = typer.Option(None, help="Checkpoints (100 iterations each) without a better "
                                           "validation accuracy before training stops (default 10)."),
    seed: int = typer.Option(0),
) -> None:
    """Meta-train a baseline on a benchmark's train classes until its accuracy on held-out train
    classes stops improving, with checkpoints (resumable) and a learning curve."""
    from ..baselines.train import DEFAULT_ITERATIONS, TrainConfig, train_baseline

    if resolution not in (56, 84):
        raise MitsubaP3Error("--resolution must be 56 or 84 (the paper's inputs)")
    config = TrainConfig(method=method, resolution=resolution, k_shot=k_shot, second_order=second_order, seed=seed,
                         iterations=DEFAULT_ITERATIONS.get(method, 20000) if iterations is None else iterations,
                         **{k: v for k, v in (("validation_classes", validation_classes), ("patience", patience))
                            if v is not None})
    bar, update = progress_bar(f"{method} {resolution}")
    with bar:
        state = train_baseline(dataset, out, config, progress=update)
    last = state.curve[-100:]
    best = state.best_validation
    typer.echo(json.dumps({"out": str(out), "iterations": state.iteration, "early_stopped": state.stopped,
                           "kept_iteration": state.kept_iteration,
                           "best_validation_accuracy": None if best is None else round(best, 4),
                           "recent_loss": round(float(np.mean([c[1] for c in last])), 4),
                           "recent_query_accuracy": round(float(np.mean([c[2] for c in last])), 4),
                           "learning_curve": str(out / "learning_curve.png")}, indent=2))


@baseline_app.command("train-all")
def baseline_train_all(
    data: Path = typer.Option(Path("data"), "--data", help="Folder of the benchmark folders (data/fsclvr, ...)."),
    out: Path = typer.Option(Path("out/reproduction"), "-o", "--out", help="The reproduction's folder: trainings in "
                             "OUT/baselines, scores in OUT/runs (reproduce's default; resumes)."),
    benchmarks: str = typer.Option("fsclvr,dark,room", help="Comma-separated benchmarks (fsclvr's networks are "
                                   "also scored on ood)."),
    methods: str = typer.Option("protonets,maml", help="Comma-separated: protonets, maml."),
    resolutions: str = typer.Option("56,84", help="Comma-separated input sizes: 56, 84."),
    episodes: int = typer.Option(100, help="Test episodes per setting."),
    patience: Optional[int] = typer.Option(None, help="Checkpoints without a better validation accuracy before "
                                           "a training stops (default 10)."),
    iterations: Optional[int] = typer.Option(None, help="Cap on meta-iterations (default 20000)."),
    rescore: bool = typer.Option(False, "--rescore", help="Score again where a score exists."),
) -> None:
    """Every baseline of the paper's table, trained to early stopping and scored into the reproduction's run
    folders, resumable: a killed run continues where it stopped. Prints one JSON line per baseline."""
    from ..baselines.train import train_all
    from ..files import refuse_protected_folder

    sizes = [int(r) for r in resolutions.split(",") if r.strip()]
    if not sizes or any(r not in (56, 84) for r in sizes):
        raise MitsubaP3Error(f"--resolutions must be 56 and/or 84 (the paper's inputs); got {resolutions!r}")
    refuse_protected_folder(out, "mitsuba-p3 baseline train-all")
    for record in train_all(data, out, [b.strip() for b in benchmarks.split(",") if b.strip()],
                            [m.strip() for m in methods.split(",") if m.strip()], sizes, episodes, patience,
                            iterations, rescore, progress_bar=progress_bar):
        typer.echo(json.dumps(record), nl=True)


@baseline_app.command("evaluate")
def baseline_evaluate(
    trained: Path = typer.Argument(..., help="Training folder (mitsuba-p3 baseline train)."),
    dataset: Path = typer.Argument(..., help="Benchmark folder; its test episodes are used."),
    out: Path = typer.Option(..., "-o", "--out", help="Evaluation run folder (results go to baselines/)."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting (same as evaluate)."),
) -> None:
    """Accuracy on the same test episodes as P3/NP3; the evaluation tables pick it up."""
    from ..baselines.train import evaluate_baseline

    bar, update = progress_bar("episodes")
    with bar:
        result = evaluate_baseline(trained, dataset, out, episodes, progress=update)
    typer.echo(json.dumps({result["model"]: {k: round(100 * v["mean"], 1) for k, v in result["accuracy"].items()}},
                          indent=2))


@baseline_app.command("frozen")
def baseline_frozen(
    dataset: Path = typer.Argument(..., help="Benchmark folder; its test episodes are scored."),
    out: Path = typer.Option(..., "-o", "--out", help="Evaluation run folder (results go to baselines/frozen-*.json)."),
    choose_on: Optional[Path] = typer.Option(None, help="Benchmark whose train classes choose the layer, the probe's "
                                                        "C and the centring mean (default: DATASET's own; ood has "
                                                        "none: give fsclvr's)."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting (same as evaluate)."),
) -> None:
    """Frozen pretrained VGG16 features, classified by nearest centroid and by a linear probe: chosen
    on held-out train classes, scored on the same test episodes as P3/NP3 (no training)."""
    from ..baselines.frozen import score_benchmark
    from ..files import refuse_protected_folder

    refuse_protected_folder(out, "mitsuba-p3 baseline frozen")
    bar, update = progress_bar("episodes")
    with bar:
        results = score_benchmark(dataset, out, choose_on, episodes, progress=update)
    typer.echo(json.dumps({r["model"]: {"layer": r["frozen"]["layer"], "C": r["frozen"]["c"],
                                        **{k: round(100 * v["mean"], 1) for k, v in r["accuracy"].items()}}
                           for r in results}, indent=2))


@baseline_app.command("status")
def baseline_status(
    trained: list[Path] = typer.Argument(..., help="Training folders, or folders of them (e.g. results/baselines)."),
    runs: Optional[Path] = typer.Option(None, help="The reproduction's run folders (OUT/runs), where "
                                        "baseline train-all writes the test scores."),
    figure: Optional[Path] = typer.Option(None, help="Also draw every baseline's validation curve in one PNG."),
) -> None:
    """Where each baseline's training is (iterations, kept iteration, best validation accuracy, early
    stopped or not) and, once scored, its test accuracy: a markdown table from the checkpoints."""
    from ..baselines.status import status_of, status_table, training_folders, validation_figure

    rows = [status_of(folder, runs) for folder in training_folders(trained)]
    typer.echo(status_table(rows))
    if figure is not None:
        typer.echo(f"validation curves: {validation_figure(rows, figure)}")


@baseline_app.command("convert")
def baseline_convert(
    trained: list[Path] = typer.Argument(..., help="Training folders holding an older checkpoint.pkl you trust."),
) -> None:
    """Convert older pickle checkpoints (checkpoint.pkl) to today's JSON + npz files, which load without
    running code. Reading a pickle runs whatever it holds: convert only checkpoints you made or trust."""
    from ..baselines.train import convert_legacy_checkpoint

    for folder in trained:
        typer.echo(f"converted: {convert_legacy_checkpoint(folder)}")
