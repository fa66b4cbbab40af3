"""How far each baseline's training got, from its checkpoint alone: one row per training folder.

A baseline trains to early stopping over several runs (``mitsuba-p3 baseline train-all`` resumes its
checkpoint), so the question "where is it?" comes back each time. The answer is in
the folder: the checkpoint says the iterations done, the validation accuracy at every checkpoint,
the kept (best) iteration and whether training stopped; a score file, if the kept network has been
scored, says its test accuracy. :func:`status_table` writes the rows as the markdown table the
results pages show, so that table is made by a command, not by hand, and :func:`validation_figure`
draws every baseline's validation accuracy against its iterations in one figure (each folder's
``learning_curve.png`` has its own, with the training loss).

Scores are looked up in the folder's ``scores.json`` and, with ``runs``, in
``RUNS/V/baselines/METHOD-R.json`` (where ``mitsuba-p3 baseline train-all`` writes them; V is the folder's name
up to ``-METHOD-R``, the script's naming). A score of an earlier kept iteration than the
checkpoint's is stale and not shown.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import NamedTuple

from ..errors import BaselineError
from .train import Checkpoint, TrainConfig, has_checkpoint, score_file, scored_benchmarks, since_best

SETTINGS = ("5-way 1-shot", "5-way 5-shot", "10-way 1-shot", "10-way 5-shot")


class Status(NamedTuple):
    """One training folder: where its training is and, if scored, the kept network's test accuracy."""
    name: str
    state: str                     # early-stopped, at its cap, or training (resumable)
    iterations: int
    kept: int
    best_validation: float | None
    checkpoints_since_best: int
    patience: int
    scores: dict                   # test benchmark -> {setting: accuracy in %}
    validation: list               # (iteration, validation accuracy) per checkpoint


def training_folders(paths: list[Path]) -> list[Path]:
    """Each path that is a training folder (it holds a checkpoint), or the training folders in it."""
    found = []
    for path in map(Path, paths):
        if has_checkpoint(path):
            found.append(path)
        elif path.is_dir():
            found += sorted(p for p in path.iterdir() if has_checkpoint(p))
        else:
            raise BaselineError(f"{path} is neither a baseline's training folder nor a folder of them")
    if not found:
        raise BaselineError(f"no baseline checkpoint in {', '.join(map(str, paths))}")
    return found


def status_of(folder: Path, runs: Path | None = None) -> Status:
    """The :class:`Status` of one training folder (scores also from ``runs``, see the module docstring)."""
    state = Checkpoint.load(folder, arrays=False)
    config = TrainConfig(**state.config)
    where = "early-stopped" if state.stopped else "at its cap" if state.iteration >= config.iterations else "training"
    suffix = f"-{config.method}-{config.resolution}"
    benchmark = folder.name[:-len(suffix)] if folder.name.endswith(suffix) else folder.name
    files = {benchmark: [folder / "scores.json"]}
    if runs is not None:
        for target in scored_benchmarks(benchmark):
            files.setdefault(target, []).append(score_file(Path(runs) / target, config))
    scores = {}
    for target, candidates in files.items():
        for file in candidates:
            record = json.loads(file.read_text()) if file.is_file() else {}
            if record.get("kept_iteration") == state.kept_iteration:    # not a score of an earlier kept network
                scores[target] = {k: round(100 * v["mean"], 1) for k, v in record["accuracy"].items()}
                break
    return Status(folder.name, where, state.iteration, state.kept_iteration, state.best_validation,
                  since_best(state), config.patience, scores, list(state.validation))


def status_table(rows: list[Status]) -> str:
    """The rows as a markdown table: state, iterations, kept iteration (best validation), test scores."""
    lines = ["| baseline | state | iterations | kept (best validation) | test: 5w1s / 5w5s / 10w1s / 10w5s |",
             "|---|---|---|---|---|"]
    for row in rows:
        best = "-" if row.best_validation is None else f"{row.kept} ({row.best_validation:.4g})"
        state = row.state if row.state != "training" else \
            f"training ({row.checkpoints_since_best} of {row.patience} checkpoints since the best)"
        scored = "; ".join(f"{target} " + " / ".join(f"{scores[s]:.1f}" if s in scores else "-" for s in SETTINGS)
                           for target, scores in row.scores.items()) or "not scored"
        lines.append(f"| `{row.name}` | {state} | {row.iterations} | {best} | {scored} |")
    return "\n".join(lines)


def validation_figure(rows: list[Status], path: Path) -> Path:
    """Every baseline's validation accuracy per checkpoint, one line each (colour: benchmark, dashes:
    84 px, marker: method), the kept checkpoint circled and a stopped run's last point crossed."""
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    figure, ax = plt.subplots(figsize=(8, 4))
    benchmarks = sorted({row.name.split("-")[0] for row in rows})
    for row in rows:
        if not row.validation:
            continue
        iterations, accuracy = zip(*row.validation)
        colour = f"C{benchmarks.index(row.name.split('-')[0])}"
        ax.plot(iterations, accuracy, ls="--" if row.name.endswith("-84") else "-", color=colour, lw=1.2,
                marker="s" if "-maml-" in row.name else "o", ms=2.5, label=row.name)
        ax.plot([row.kept], [dict(row.validation)[row.kept]], "o", ms=9, mfc="none", color=colour)
        if row.state == "early-stopped":
            ax.plot(iterations[-1:], accuracy[-1:], "x", ms=7, color=colour)
    ax.set_xlabel("meta-training iteration")
    ax.set_ylabel("accuracy on held-out train classes")
    ax.set_title("Baselines: validation accuracy (circle: kept, cross: early-stopped)")
    ax.legend(fontsize=7, loc="upper left", bbox_to_anchor=(1.01, 1.0))
    ax.grid(alpha=0.3)
    return save_figure(figure, path)
