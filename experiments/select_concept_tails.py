"""Should a concept's kernels have heavy tails? Decided on *train* classes.

A protoprogram widens each posterior by the concept spread, the pooled within-class covariance of
train posteriors' means, with Gaussian kernels. A metal's colour posterior moves with what it mirrors,
so two images of one metal class can lie many spreads apart; under a Gaussian kernel such a gap costs
its squared distance, tens of nats that drown the shape and material terms (docs/notebook.md, "Dark's
1-shot misses are the distance's"). A Student-t kernel of the same covariance is the predictive density
of a hierarchical model whose within-class scale is itself uncertain: it charges a large gap about its
log. Its degrees of freedom and scales are *fitted*, as those under which the differences between two
train images' posterior means of one class are most likely (``concepts.fit_tail``), not chosen by
accuracy; this script asks whether fitted tails improve held-out train classes' episodes. Three forms:
one degrees of freedom shared by every property (``fit_spread(..., tails=True)``), one per property,
and a first form with one per property and the Gaussian's covariance (the scale tied to the degrees
of freedom, which must then exceed 2).

The train classes are halved (``--splits`` random halvings); each half's episodes use the spread (and
tails) fitted on the other half, as ``select_kind_term.py`` does. Reads an evaluation's cached train
posteriors only.

    python experiments/select_concept_tails.py data/dark-lo out/eval-dark-tinted [--episodes 200] [--splits 4]
        [--profile-only]
"""
from __future__ import annotations

import argparse
import itertools
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.concepts import (CONTINUOUS, ConceptSpread, DistanceConfig, ProtoProgram, _kl_matrix, fit_spread,
                                 fit_student, fit_tail, student_log_likelihood)
from mitsuba_p3.evaluate.jobs import cached_train_posteriors
from mitsuba_p3.evaluate.metrics import held_out_episodes
from mitsuba_p3.evaluate.run import train_shapes


def episode_accuracy(images: dict, n_way: int, k_shot: int, count: int, seed: int, kl) -> float:
    """Accuracy of seeded episodes among ``images`` (class -> image indices), as
    :func:`mitsuba_p3.evaluate.metrics.held_out_accuracy` draws them; ``kl(query, shots)`` is the
    distance of a query image from the class program of the (sorted) shots."""
    correct = []
    for chosen, picks in held_out_episodes({c: len(g) for c, g in images.items()}, n_way, k_shot, count, seed):
        shots = [tuple(sorted(images[c][s] for s in pick[:-1])) for c, pick in zip(chosen, picks)]
        queries = [images[c][pick[-1]] for c, pick in zip(chosen, picks)]
        distances = np.array([[kl(q, s) for s in shots] for q in queries])
        correct += list(np.argmin(distances, axis=1) == np.arange(n_way))
    return float(np.mean(correct))


def distance_table(programs: dict, images: dict, k_shot: int, config: DistanceConfig) -> dict:
    """The distance of every image from every K-shot class program among ``images`` (class -> indices),
    computed once (each program's draws are seeded, so an episode would compute the same numbers)."""
    shots = sorted({tuple(sorted(group)) for group in
                    (combo for c in images for combo in itertools.combinations(images[c], k_shot))})
    queries = sorted(i for c in images for i in images[c])
    classes = [ProtoProgram.merge([programs[i] for i in shot]) for shot in shots]
    matrix = sum(_kl_matrix(classes, [programs[q] for q in queries], config).values())   # (queries, classes)
    return {(q, shot): matrix[a, b] for a, q in enumerate(queries) for b, shot in enumerate(shots)}


MATCHED_GRID = (2.5, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0, np.inf)


def matched_log_likelihood(differences: np.ndarray, covariance: np.ndarray, dof: float) -> float:
    """log likelihood of differences (n, d) under a zero-mean Student-t of the given covariance."""
    scale = covariance + np.eye(len(covariance)) * 1e-12
    return student_log_likelihood(differences, scale if np.isinf(dof) else scale * (dof - 2.0) / dof, dof)


def moment_matched(programs: dict, shapes: dict) -> ConceptSpread:
    """The Gaussian spread with Student-t kernels of its covariance (scale (nu - 2) / nu of it), nu fitted on
    the within-class differences of posterior means."""
    gaussian = fit_spread(programs, shapes)
    covariance, tails = {}, {}
    for name in CONTINUOUS:
        differences = within_class_differences(programs, name)
        dof = max(MATCHED_GRID, key=lambda v: matched_log_likelihood(differences, 2 * gaussian.covariance[name], v))
        tails[name] = dof
        covariance[name] = gaussian.covariance[name] * (1.0 if np.isinf(dof) else (dof - 2.0) / dof)
    return ConceptSpread(covariance, gaussian.class_error, gaussian.images, gaussian.classes, tails)


def within_class_differences(programs: dict, name: str) -> np.ndarray:
    return np.stack([np.mean(a.samples[name], axis=0) - np.mean(b.samples[name], axis=0)
                     for group in programs.values() for i, a in enumerate(group) for b in group[i + 1:]])


def per_property_tails(programs: dict, shapes: dict) -> ConceptSpread:
    """Student-t kernels whose degrees of freedom and scale are fitted for each property on its own."""
    gaussian = fit_spread(programs, shapes)
    fits = {name: fit_tail([within_class_differences(programs, name)]) for name in CONTINUOUS}
    return ConceptSpread({name: fit[1][0] for name, fit in fits.items()}, gaussian.class_error, gaussian.images,
                         gaussian.classes, {name: fit[0] for name, fit in fits.items()})


def print_profile(programs: dict) -> None:
    """Each property's log likelihood of its within-class differences as a function of the degrees of freedom
    (the scale fitted by EM at each): where the maximum lies, and how far a Gaussian is from it."""
    for name in CONTINUOUS:
        x = within_class_differences(programs, name)
        row = {dof: round(fit_student(x, dof)[1], 1) for dof in (0.5, 0.75, 1.0, 1.5, 2.0, 3.0, 6.0, np.inf)}
        print(f"profile {name} ({len(x)} pairs): " + ", ".join(f"nu {k:g}: {v}" for k, v in row.items()))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path, help="an evaluation run holding train posteriors")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--splits", type=int, default=4, help="random halvings of the train classes")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--profile-only", action="store_true",
                        help="only print each property's log likelihood against the degrees of freedom")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    config = DistanceConfig()
    posteriors = {c: g for c, g in cached_train_posteriors(dataset, args.run, "p3", config.max_points).items() if g}
    programs = {c: [p.program for p in g.values()] for c, g in posteriors.items()}
    shapes = train_shapes(dataset)
    print(f"{sum(map(len, posteriors.values()))} train posteriors of {len(posteriors)} classes")
    print_profile(programs)
    if args.profile_only:
        return
    print("tails fitted on every train class: shared " + json.dumps(fit_spread(programs, shapes, tails=True).to_json()["tails"])
          + ", per property " + json.dumps(per_property_tails(programs, shapes).to_json()["tails"])
          + ", moment-matched " + json.dumps(moment_matched(programs, shapes).to_json()["tails"]))
    names = sorted(posteriors)
    settings = [(5, 1), (10, 1)] + ([(5, 2), (10, 2)] if min(len(g) for g in posteriors.values()) >= 3 else [])
    variants = {"gaussian": lambda p: fit_spread(p, shapes), "moment-matched tails": lambda p: moment_matched(p, shapes),
                "tails per property": lambda p: per_property_tails(p, shapes),
                "shared tails": lambda p: fit_spread(p, shapes, tails=True)}
    cells = {label: [] for label in variants}
    for split in range(args.splits):
        order = list(np.random.default_rng([args.seed, split]).permutation(names))
        folds = [order[:len(order) // 2], order[len(order) // 2:]]
        for f, fold in enumerate(folds):
            other = {c: programs[c] for c in folds[1 - f]}
            fitted = {}
            for label, fit in variants.items():
                spread = fitted[label] = fit(other)
                held = {i: p.program.with_spread(spread) for c in fold for i, p in posteriors[c].items()}
                images = {c: sorted(posteriors[c]) for c in fold}
                tables = {k: distance_table(held, images, k, config) for k in sorted({k for _, k in settings})}
                cells[label].append([episode_accuracy(images, n, k, args.episodes, args.seed + split,
                                                      lambda q, s, k=k: tables[k][(q, s)]) for n, k in settings])
            print(f"split {split} half {f}: " + "; ".join(
                f"{label} {np.round(cells[label][-1], 3).tolist()} {fitted[label].tails or ''}" for label in cells),
                flush=True)
    names_out = [f"{n}-way {k}-shot" for n, k in settings]
    report = {label: dict(zip(names_out, (100 * np.mean(v, axis=0)).round(2).tolist())) for label, v in cells.items()}
    for label in list(variants)[1:]:
        diff = 100 * (np.array(cells[label]) - np.array(cells["gaussian"]))
        report[f"{label} - gaussian, mean and sd over halves"] = {
            n: [round(float(m), 2), round(float(s), 2)] for n, m, s in
            zip(names_out, diff.mean(axis=0), diff.std(axis=0, ddof=1))}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
