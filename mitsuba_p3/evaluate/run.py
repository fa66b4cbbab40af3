"""The evaluation driver: posteriors (cached, resumable), episodes, pose errors, tables."""
from __future__ import annotations

import csv
from pathlib import Path
from typing import Callable

from ..benchmarks.dataset import load_dataset
from ..files import atomic_json, atomic_open
from ..fit.attributes import rules_for
from ..fit.model import FittedModel
from .config import EvaluationConfig
from .jobs import CachedPosterior, check_run, compute_posteriors, posterior_path
from .metrics import (accuracy_of, attribute_recovery, classify_episodes, feasible_settings, pose_errors, pose_summary,
                      setting_name)
from .tables import tables_dir, write_tables


def evaluate(dataset_dir: str | Path, model_dir: str | Path, run_dir: str | Path,
             config: EvaluationConfig | None = None,
             progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Posteriors (resumable), episodes, pose errors and tables; returns the results."""
    import numpy as np

    config = config or EvaluationConfig()
    dataset = load_dataset(dataset_dir)
    run_dir = Path(run_dir)
    check_run(run_dir, dataset, Path(model_dir), config)
    compute_posteriors(dataset, Path(model_dir), run_dir, config,
                       (lambda done, total: progress("posteriors", done, total)) if progress else None)
    fewest = min(len(dataset.shots_of(c)) for c in dataset.classes("test"))
    settings = feasible_settings(len(dataset.classes("test")), fewest, config.queries_per_class)
    rules = rules_for(FittedModel(model_dir), dataset)
    results, predictions, attributes = {}, [], []
    for likelihood in config.likelihoods:
        cached = {shot.index: CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index),
                                                   config.distance.max_points)
                  for shot in dataset.split("test")}
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
