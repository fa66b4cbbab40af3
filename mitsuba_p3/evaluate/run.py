"""The evaluation driver: posteriors (cached, resumable), episodes, pose errors, tables."""
from __future__ import annotations

import csv
import json
from dataclasses import replace
from pathlib import Path
from typing import Callable

from ..benchmarks.dataset import Dataset, load_dataset
from ..concepts import ConceptSpread, fit_spread
from ..errors import EvaluationError
from ..files import atomic_json, atomic_open, folder_lock
from ..fit.attributes import rules_for
from ..fit.model import FittedModel
from .config import EvaluationConfig
from .jobs import (CachedPosterior, PosteriorMisfits, check_run, check_scheduler, compute_posteriors,
                   posterior_path, rules_with_train_posteriors)
from .metrics import (accuracy_of, attribute_recovery, classify_episodes, pose_errors, pose_summary, setting_name,
                      test_settings)
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


def spread_file(run_dir: Path, likelihood: str, per_class: int, tails: bool = True) -> Path:
    """RUN/spread-LIKELIHOOD-N.json (with fitted tails) or RUN/spread-LIKELIHOOD-N-gaussian.json."""
    return Path(run_dir) / f"spread-{likelihood}-{per_class}{'' if tails else '-gaussian'}.json"


def _borrowed_spread(dataset: Dataset, run_dir: Path, likelihood: str, per_class: int,
                     spread_from: Path | None, tails: bool = True) -> Path:
    """The spread file a data set without train classes takes (from ``spread_from``, else its own run)."""
    source = spread_file(spread_from or run_dir, likelihood, per_class, tails)
    if not source.is_file():
        raise EvaluationError(f"{dataset.root} has no train classes to fit the concept spread on: pass "
                              "--spread-from RUN, the evaluation of the model's own benchmark with the same "
                              f"settings (it holds {source.name}), or --spread-shots 0")
    if tails and not json.loads(source.read_text()).get("tails"):
        raise EvaluationError(f"{source} was written before concept spreads had fitted tails: evaluate "
                              f"{source.parent} again (its posteriors are cached) or pass --gaussian-concepts")
    return source


def run_spread(dataset: Dataset, run_dir: Path, likelihood: str, config: EvaluationConfig,
               spread_from: Path | None = None) -> ConceptSpread | None:
    """The concept spread of a run's cached train posteriors (written to RUN/spread-LIKELIHOOD-N.json),
    or None when the distance asks for the paper's programs. A data set without train classes (ood,
    scored with another benchmark's model) takes the spread of ``spread_from``, that benchmark's run."""
    per_class, tails = config.distance.spread_shots, config.distance.tails
    if not per_class:
        return None
    if not dataset.classes("train"):
        spread = ConceptSpread.from_json(json.loads(_borrowed_spread(dataset, run_dir, likelihood, per_class,
                                                                     spread_from, tails).read_text()))
        atomic_json(spread_file(run_dir, likelihood, per_class, tails), spread.to_json())
        return spread
    programs = {name: [CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index),
                                            config.distance.max_points).program
                       for shot in dataset.shots_of(name)[:per_class]] for name in dataset.classes("train")}
    spread = fit_spread(programs, train_shapes(dataset), tails=tails)
    atomic_json(spread_file(run_dir, likelihood, per_class, tails), spread.to_json())
    return spread


def _material_rule_source(dataset: Dataset, run_dir: Path, model_dir: Path, misfits: PosteriorMisfits,
                          spread_from: Path | None) -> tuple | None:
    """Where the material rule is learnt: (data set, run, misfits) of the train posteriors. A data set
    without train classes (ood) learns it where it borrows the concept spread, from the train
    posteriors of ``spread_from`` and that run's own data set; None (the fit's rule) without either."""
    if dataset.classes("train"):
        return dataset, run_dir, misfits
    record = Path(spread_from or "") / "run.json"
    if spread_from is None or not record.is_file():
        return None
    source = load_dataset(json.loads(record.read_text())["dataset"])
    return source, Path(spread_from), PosteriorMisfits(source, model_dir)


def sample_spread(dataset_dir: str | Path, model_dir: str | Path, run_dir: str | Path, config: EvaluationConfig,
                  progress: Callable[[str, int, int], None] | None = None) -> None:
    """Only the concept-spread part of an evaluation run: its train posteriors (cached, resumable, shared
    with a full evaluation of the same run) and RUN/spread-LIKELIHOOD-N.json."""
    dataset = load_dataset(dataset_dir)
    check_run(Path(run_dir), dataset, Path(model_dir), config)
    with folder_lock(run_dir, "mitsuba-p3 evaluate"):
        compute_posteriors(dataset, Path(model_dir), Path(run_dir), config,
                           (lambda done, total: progress("spread posteriors", done, total)) if progress else None,
                           spread_shots(dataset, config.distance.spread_shots))
        for likelihood in config.likelihoods:
            run_spread(dataset, Path(run_dir), likelihood, config)


def evaluate(dataset_dir: str | Path, model_dir: str | Path, run_dir: str | Path,
             config: EvaluationConfig | None = None,
             progress: Callable[[str, int, int], None] | None = None,
             spread_from: str | Path | None = None) -> dict:
    """Posteriors (resumable), episodes, pose errors and tables; returns the results. ``spread_from``:
    the run whose concept spread a data set without train classes uses (see :func:`run_spread`)."""
    import numpy as np

    config = config or EvaluationConfig()
    dataset = load_dataset(dataset_dir)
    run_dir = Path(run_dir)
    settings = test_settings(dataset, config.queries_per_class)
    if not settings:
        raise EvaluationError(f"{dataset.root}: its {len(dataset.classes('test'))} test classes fill none of the "
                              "few-shot settings (5 or 10 classes, 1 or 5 supports "
                              f"and {config.queries_per_class} query each)")
    train = [len(dataset.shots_of(c)) for c in dataset.classes("train")]
    if config.distance.spread_shots and train and not any(n >= 2 for n in train):
        raise EvaluationError(f"{dataset.root}: fitting the concept spread needs a train class with 2 or more "
                              "images; add them, or pass --spread-shots 0 for the paper's programs")
    if config.distance.spread_shots and not train:
        for likelihood in config.likelihoods:
            _borrowed_spread(dataset, run_dir, likelihood, config.distance.spread_shots, spread_from,
                             config.distance.tails)
    rules = rules_for(FittedModel(model_dir), dataset)            # the model folder is checked before any work
    if config.dask:
        check_scheduler(config.dask)
    check_run(run_dir, dataset, Path(model_dir), config)
    with folder_lock(run_dir, "mitsuba-p3 evaluate"):
        shots = [shot.index for shot in dataset.split("test")] + spread_shots(dataset, config.distance.spread_shots)
        compute_posteriors(dataset, Path(model_dir), run_dir, config,
                           (lambda done, total: progress("posteriors", done, total)) if progress else None, shots)
        results, predictions, attributes = {}, [], []
        misfits = PosteriorMisfits(dataset, Path(model_dir))       # the material rule's Phong misfits
        learn_from = _material_rule_source(dataset, run_dir, Path(model_dir), misfits, spread_from)
        for likelihood in config.likelihoods:
            spread = run_spread(dataset, run_dir, likelihood, config, spread_from)
            cached = {}
            for shot in dataset.split("test"):
                post = CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index),
                                            config.distance.max_points)
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
            rules_here = (rules_with_train_posteriors(rules, learn_from[0], learn_from[1], likelihood, learn_from[2])
                          if learn_from else rules)
            rows, recovered = attribute_recovery(dataset, cached, rules_here, misfits)
            # the rule as learnt here, for `mitsuba-p3 infer --material-rule` on new images
            atomic_json(run_dir / f"material-rule-{likelihood}.json", rules_here.material_record())
            attributes += [{"model": likelihood, **row} for row in rows]
            results[likelihood] = {
                "accuracy": accuracy, "adi_per_class": per_class, "adi": overall, "attributes": recovered,
                "seconds_per_image": float(np.mean([c.seconds for c in cached.values()])),
                **convergence(cached.values()),
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
                                           "distance": list(config.distance.properties),
                                           "kl": config.distance.direction, "concept_tails": config.distance.tails,
                                           "files": files})
        return results


def convergence(cached) -> dict:
    """What shows each sampler's own failure, over a run's posteriors: MH's R-hat across chains (the
    median of each posterior's largest); SMC's island gap, the spread of the leading hypothesis's
    independent runs' log evidence (median, 90th percentile, share above 10 nats). A figure that
    cannot be made (no MH posterior, or SMC caches from before the gap was kept) is left out."""
    import numpy as np

    cached = list(cached)
    # an SMC cache (it has log evidence) made before SMC stopped cutting its pool into chains holds an
    # R-hat of that pool: not a diagnostic, so not reported
    r_hats = [c.max_r_hat for c in cached if c.log_evidence is None and np.isfinite(c.max_r_hat)]
    gaps = [c.island_gap for c in cached if np.isfinite(c.island_gap)]
    out = {}
    if r_hats:
        out["max_r_hat_median"] = float(np.median(r_hats))
    if gaps:
        out.update({"island_gap_median": float(np.median(gaps)), "island_gap_p90": float(np.percentile(gaps, 90)),
                    "island_gap_over_10": float(np.mean(np.asarray(gaps) > 10.0))})
    factors = [f for f in (getattr(c, "log_bayes_factor_object", np.nan) for c in cached) if np.isfinite(f)]
    if factors:
        # images the empty floor explains better than one object: each shows an object, so this should be 0
        out["unexplained_share"] = float(np.mean(np.asarray(factors) < 0))
    return out
