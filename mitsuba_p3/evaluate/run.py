"""The evaluation driver: posteriors (cached, resumable), episodes, pose errors, tables."""
from __future__ import annotations

import csv
from dataclasses import replace
from pathlib import Path
from typing import Callable

from ..benchmarks.dataset import Dataset, load_dataset
from ..concepts import ConceptSpread, fit_spread
from ..files import atomic_json, atomic_open
from ..fit.attributes import rules_for
from ..fit.model import FittedModel
from .config import EvaluationConfig
from .jobs import CachedPosterior, check_run, compute_posteriors, posterior_path
from .metrics import (accuracy_of, attribute_recovery, classify_episodes, feasible_settings, pose_errors, pose_summary,
                      setting_name)
from .tables import tables_dir, write_tables


def train_shapes(dataset: Dataset) -> dict[str, int | None]:
    """Each train class's true shape as an index into SHAPES (None for a shape outside them)."""
    from ..shapes import SHAPES

    labels = dataset.class_labels
    return {name: SHAPES.index(labels[name].shape) if labels[name].shape in SHAPES else None
            for name in dataset.classes("train")}


def spread_shots(dataset: Dataset, per_class: int) -> list[int]:
    """The train images whose posteriors fit the concept spread: the first ``per_class`` of each train class."""
    return [shot.index for name in dataset.classes("train") for shot in dataset.shots_of(name)[:per_class]]


def run_spread(dataset: Dataset, run_dir: Path, likelihood: str, config: EvaluationConfig) -> ConceptSpread | None:
    """The concept spread of a run's cached train posteriors (written to RUN/spread-LIKELIHOOD-N.json),
    or None when the distance asks for the paper's programs."""
    per_class = config.distance.spread_shots
    if not per_class:
        return None
    programs = {name: [CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index),
                                            config.distance.max_points).program
                       for shot in dataset.shots_of(name)[:per_class]] for name in dataset.classes("train")}
    spread = fit_spread(programs, train_shapes(dataset))
    atomic_json(run_dir / f"spread-{likelihood}-{per_class}.json", spread.to_json())
    return spread


def evaluate(dataset_dir: str | Path, model_dir: str | Path, run_dir: str | Path,
             config: EvaluationConfig | None = None,
             progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Posteriors (resumable), episodes, pose errors and tables; returns the results."""
    import numpy as np

    config = config or EvaluationConfig()
    dataset = load_dataset(dataset_dir)
    run_dir = Path(run_dir)
    check_run(run_dir, dataset, Path(model_dir), config)
    shots = [shot.index for shot in dataset.split("test")] + spread_shots(dataset, config.distance.spread_shots)
    compute_posteriors(dataset, Path(model_dir), run_dir, config,
                       (lambda done, total: progress("posteriors", done, total)) if progress else None, shots)
    fewest = min(len(dataset.shots_of(c)) for c in dataset.classes("test"))
    settings = feasible_settings(len(dataset.classes("test")), fewest, config.queries_per_class)
    rules = rules_for(FittedModel(model_dir), dataset)
    results, predictions, attributes = {}, [], []
    for likelihood in config.likelihoods:
        spread = run_spread(dataset, run_dir, likelihood, config)
        cached = {}
        for shot in dataset.split("test"):
            post = CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index), config.distance.max_points)
            cached[shot.index] = replace(post, program=post.program.with_spread(spread))
        accuracy = {}
        for step, (n_way, k_shot) in enumerate(settings):
            if progress:
                progress(f"episodes {likelihood}", step, len(settings))
            rows = [{**row, "model": likelihood} for row in classify_episodes(dataset, cached, n_way, k_shot, config)]
            if progress:
                progress(f"episodes {likelihood}", step + 1, len(settings))
            predictions += rows
            accuracy[setting_name(n_way, k_shot)] = accuracy_of(rows, config.episodes)
        per_class, overall = pose_summary(pose_errors(dataset, cached))
        rows, recovered = attribute_recovery(dataset, cached, rules)
        attributes += [{"model": likelihood, **row} for row in rows]
        results[likelihood] = {
            "accuracy": accuracy, "adi_per_class": per_class, "adi": overall, "attributes": recovered,
            "seconds_per_image": float(np.mean([c.seconds for c in cached.values()])),
            "max_r_hat_median": float(np.median([c.max_r_hat for c in cached.values()])),
        }
    out = tables_dir(run_dir, config.distance)
    out.mkdir(parents=True, exist_ok=True)
    with atomic_open(out / "predictions.csv") as f:
        if predictions:
            writer = csv.DictWriter(f, fieldnames=list(predictions[0]))
            writer.writeheader()
            writer.writerows(predictions)
    with atomic_open(out / "attributes.csv") as f:
        writer = csv.DictWriter(f, fieldnames=list(dict.fromkeys(k for row in attributes for k in row)))
        writer.writeheader()
        writer.writerows(attributes)
    files = write_tables(out, results, baselines_dir=run_dir)
    atomic_json(out / "results.json", {"dataset": str(dataset.root), "results": results,
                                       "distance": list(config.distance.properties), "files": files})
    return results
