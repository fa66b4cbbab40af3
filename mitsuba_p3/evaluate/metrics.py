"""Scores of an evaluation: few-shot settings, accuracies with intervals, calibration, pose errors.

Shared by every model evaluated on a benchmark's episodes (P3, NP3 and the
neural baselines), so their numbers are computed the same way.
"""
from __future__ import annotations

import numpy as np

from ..benchmarks.dataset import Dataset
from ..benchmarks.episodes import sample_episodes
from ..concepts import DistanceConfig, ProtoProgram, classify_many

SETTINGS = ((5, 1), (5, 5), (10, 1), (10, 5))   # (N-way, K-shot), the paper's four


def setting_name(n_way: int, k_shot: int) -> str:
    """The key of a setting in every table: ``"5-way 1-shot"``."""
    return f"{n_way}-way {k_shot}-shot"


def feasible_settings(n_classes: int, fewest_shots: int, queries_per_class: int = 1) -> list[tuple[int, int]]:
    """The settings of :data:`SETTINGS` that ``n_classes`` classes with at least ``fewest_shots``
    images each can fill (K supports and the queries per class)."""
    return [(n, k) for n, k in SETTINGS if n <= n_classes and k + queries_per_class <= fewest_shots]


def test_settings(dataset: Dataset, queries_per_class: int = 1) -> list[tuple[int, int]]:
    """The settings a data set's test classes fill (:func:`feasible_settings` of its smallest class)."""
    test = dataset.classes("test")
    fewest = min((len(dataset.shots_of(c)) for c in test), default=0)
    return feasible_settings(len(test), fewest, queries_per_class)


def interval95(values) -> tuple[float, float]:
    """Mean and the half-width of its 95% normal-approximation interval."""
    values = np.asarray(values, np.float64)
    half = 1.96 * values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")
    return float(values.mean()), float(half)


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> tuple[float, list]:
    """ECE over equal-width confidence bins, and the bins' (mean confidence, accuracy, count)."""
    confidence, correct = np.asarray(confidence, float), np.asarray(correct, float)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(confidence, edges[1:-1]), 0, bins - 1)
    ece, table = 0.0, []
    for b in range(bins):
        members = which == b
        if members.any():
            gap = abs(correct[members].mean() - confidence[members].mean())
            ece += members.mean() * gap
            table.append((float(confidence[members].mean()), float(correct[members].mean()), int(members.sum())))
        else:
            table.append((float("nan"), float("nan"), 0))
    return float(ece), table


def classify_episode(cached: dict, episode, distance: DistanceConfig) -> np.ndarray:
    """(queries, classes) probabilities of one episode: each class's program merged from its support shots
    (``cached``: image index -> an object with a ``program``)."""
    programs = [ProtoProgram.merge([cached[i].program for i in shots]) for shots in episode.support]
    return classify_many(programs, [cached[index].program for index, _ in episode.queries], distance)


def classify_episodes(dataset: Dataset, cached: dict, n_way: int, k_shot: int, config) -> list[dict]:
    """Predictions for every query of the setting's episodes (``cached``: image index -> an object
    with a ``program``; ``config``: an :class:`~mitsuba_p3.evaluate.config.EvaluationConfig`)."""
    rows = []
    for number, episode in enumerate(sample_episodes(dataset, n_way, k_shot, config.episodes, config.episode_seed,
                                                     config.queries_per_class)):
        every = classify_episode(cached, episode, config.distance)
        for (index, truth), probabilities in zip(episode.queries, every):
            rows.append({"n_way": n_way, "k_shot": k_shot, "episode": number, "query": index, "truth": truth,
                         "predicted": int(np.argmax(probabilities)), "confidence": float(probabilities.max()),
                         "p_true": float(probabilities[truth])})
    return rows


def held_out_episodes(sizes: dict[str, int], n_way: int, k_shot: int, episodes: int, seed: int):
    """The seeded draws of :func:`held_out_accuracy` over classes of ``sizes`` (class -> how many images):
    per episode, the chosen classes and, per class, the indices of its K shots followed by its query's."""
    rng = np.random.default_rng([seed, n_way])
    names = sorted(sizes)
    for _ in range(episodes):
        chosen = [names[i] for i in rng.choice(len(names), size=n_way, replace=False)]
        yield chosen, [rng.choice(sizes[c], size=k_shot + 1, replace=False) for c in chosen]


def held_out_accuracy(programs: dict[str, list[ProtoProgram]], n_way: int, episodes: int, seed: int,
                      config: DistanceConfig, k_shot: int = 1) -> float:
    """Mean accuracy of seeded N-way K-shot episodes over the classes of ``programs`` (class -> its
    shots' programs, K + 1 or more): per chosen class K shots, merged, are the support and another
    is the query. For choices made on train classes."""
    short = [c for c in sorted(programs) if len(programs[c]) < k_shot + 1]
    if short:
        raise ValueError(f"{k_shot}-shot episodes need {k_shot + 1} programs per class; "
                         f"{', '.join(short[:3])}{' ...' if len(short) > 3 else ''} have fewer")
    correct = []
    for chosen, picks in held_out_episodes({c: len(p) for c, p in programs.items()}, n_way, k_shot, episodes, seed):
        support = [ProtoProgram.merge([programs[c][s] for s in pick[:-1]]) for c, pick in zip(chosen, picks)]
        queries = [programs[c][pick[-1]] for c, pick in zip(chosen, picks)]
        probabilities = classify_many(support, queries, config)
        correct += list(np.argmax(probabilities, axis=1) == np.arange(n_way))
    return float(np.mean(correct))


def pose_errors(dataset: Dataset, cached: dict) -> list[dict]:
    """ADI of every image's posterior median position and modal yaw."""
    from ..pose import adi

    return [{"query": index, "class": dataset.shots[index].cls.name,
             "adi": adi(dataset.shots[index], post.shift, post.yaw)} for index, post in cached.items()]


def accuracy_of(rows: list[dict], episodes: int) -> dict:
    """Accuracy of one setting's predictions: mean over episodes with its 95% interval, and the
    calibration of the predicted class probabilities (ECE over 10 bins, the reliability bins)."""
    per_episode = [np.mean([r["predicted"] == r["truth"] for r in rows if r["episode"] == e]) for e in range(episodes)]
    mean, half = interval95(per_episode)
    ece, bins = expected_calibration_error([r["confidence"] for r in rows], [r["predicted"] == r["truth"] for r in rows])
    return {"mean": mean, "half_width": half, "episodes": episodes, "ece": ece, "reliability": bins}


def pose_summary(errors: list[dict]) -> tuple[dict, dict]:
    """Mean and median ADI per class and over all images."""
    summarise = lambda values: {"mean": float(np.mean(values)), "median": float(np.median(values)),  # noqa: E731
                                "images": len(values)}
    per_class = {name: summarise([e["adi"] for e in errors if e["class"] == name])
                 for name in sorted({e["class"] for e in errors})}
    return per_class, summarise([e["adi"] for e in errors])


def attribute_recovery(dataset: Dataset, cached: dict, rules, misfits=None) -> tuple[list[dict], dict]:
    """Per test image, the attributes its posterior decides (:mod:`mitsuba_p3.fit.attributes`) against its
    labels, and the summary: accuracy per attribute (shape overall and for large objects), the mean
    log probability of the true shape (class frequencies with a 0.01 pseudo-count) and the ECE of
    the shape posterior's confidence. Shapes outside the primitives (ood) are not scored. ``misfits``
    (a :class:`~mitsuba_p3.evaluate.jobs.PosteriorMisfits`) gives each posterior's Phong misfit when
    the material rule reads it (a ``misfit`` column then joins the rows)."""
    from ..shapes import SHAPES

    rows = []
    for index, post in cached.items():
        label = dataset.shots[index].cls
        misfit = misfits.for_rules(rules, index, post) if misfits is not None else None
        decided = rules.decide(post.program.samples, misfit)
        row = {"query": index, "class": label.name}
        for attribute in ("shape", "material", "size", "colour"):
            row[f"{attribute}_true"], row[f"{attribute}_decided"] = getattr(label, attribute), decided[attribute]
        if label.shape in SHAPES:
            counts = np.asarray(decided["shape_probabilities"]) * len(post.program.samples["class"]) + 0.01
            row["shape_log_score"] = float(np.log(counts[SHAPES.index(label.shape)] / counts.sum()))
            row["shape_confidence"] = float(max(decided["shape_probabilities"]))
        row["p_metal"] = decided["p_metal"]
        if misfit is not None:
            row["misfit"] = misfit
        rows.append(row)
    summary = {}
    for attribute in ("shape", "material", "size", "colour"):
        scored = [r for r in rows if attribute != "shape" or "shape_log_score" in r]
        if scored:
            summary[f"{attribute}_accuracy"] = float(np.mean([r[f"{attribute}_true"] == r[f"{attribute}_decided"]
                                                              for r in scored]))
    shaped = [r for r in rows if "shape_log_score" in r]
    if shaped:
        large = [r for r in shaped if r["size_true"] == "large"]
        if large:
            summary["shape_accuracy_large"] = float(np.mean([r["shape_true"] == r["shape_decided"] for r in large]))
        summary["shape_log_score"] = float(np.mean([r["shape_log_score"] for r in shaped]))
        summary["shape_ece"] = expected_calibration_error([r["shape_confidence"] for r in shaped],
                                                          [r["shape_true"] == r["shape_decided"] for r in shaped])[0]
    summary["images"] = len(rows)
    return rows, summary
