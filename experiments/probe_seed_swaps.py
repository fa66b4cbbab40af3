"""Which images move a few-shot cell between two evaluations of one data set (two seeds, two samplers)?

Two evaluations share their episodes, so a cell that moves between them moves because some posteriors (or the
concept spread) moved. This scores the episodes again from the runs' cached posteriors, swapping one part of run B
into run A at a time, and prints each part's move of every cell (points):

- ``B's spread``: A's posteriors with B's concept spread (``--spread FILE`` scores A's with other spread files too);
- ``B's posteriors``: every test posterior of B, with A's spread; split into the **shape-moved images** (one shape's
  share of the draws differs between A and B by more than ``--moved``: a posterior the seed decides) together, and
  the other images (their moves through the continuous draws), with each shape-moved image's own move beside its
  shape shares and island gap in both runs;
- and per continuous property how far the two runs' posterior medians lie apart, in the draws' own spread.

The parts do not add exactly (an episode can need two swapped posteriors to flip). Only the episodes that hold a
swapped image are scored again.

    python experiments/probe_seed_swaps.py data/ood-lo out/eval-ood-s0 out/eval-ood-s1 \
        [--spread results/evidence-is/ood-test-seed1/spread-p3-3.json]
"""
from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.benchmarks.episodes import sample_episodes
from mitsuba_p3.concepts import ConceptSpread
from mitsuba_p3.evaluate.config import EvaluationConfig
from mitsuba_p3.evaluate.jobs import CachedPosterior, posterior_path
from mitsuba_p3.evaluate.metrics import classify_episode, setting_name, test_settings
from mitsuba_p3.evaluate.run import spread_file
from mitsuba_p3.files import file_digest
from mitsuba_p3.shapes import SHAPES


def load_run(dataset, run: Path, config: EvaluationConfig) -> tuple[dict, ConceptSpread | None]:
    """A run's test posteriors (image -> CachedPosterior, without spread) and its concept spread."""
    if json.loads((run / "run.json").read_text()).get("labels_digest") != file_digest(dataset.root / "labels.json"):
        raise SystemExit(f"error: {run} did not evaluate {dataset.root} (its run.json's labels digest differs)")
    path = spread_file(run, "p3", config.distance.spread_shots, config.distance.tails)
    spread = ConceptSpread.from_json(json.loads(path.read_text())) if path.is_file() else None
    posteriors = {}
    for shot in dataset.split("test"):
        file = posterior_path(run, "p3", shot.index)
        if not file.exists():
            raise SystemExit(f"error: {run} has no cached posterior of test image {shot.index}")
        posteriors[shot.index] = CachedPosterior.load(file, config.distance.max_points)
    return posteriors, spread


def episode_scores(dataset, posteriors: dict, spread, settings, config: EvaluationConfig,
                   only: set | None = None, base: list | None = None) -> list[np.ndarray]:
    """Per setting, each episode's accuracy, scored with these posteriors and spread. With ``only`` (images)
    and ``base`` (the scores without the swap), only the episodes that hold one of them are scored again."""
    cached = {i: replace(p, program=p.program.with_spread(spread)) for i, p in posteriors.items()}
    out = []
    for s, (n, k) in enumerate(settings):
        episodes = sample_episodes(dataset, n, k, config.episodes, config.episode_seed, config.queries_per_class)
        scores = np.array(base[s]) if base is not None else np.zeros(len(episodes))
        for e, episode in enumerate(episodes):
            members = {i for shots in episode.support for i in shots} | {i for i, _ in episode.queries}
            if only is not None and not only & members:
                continue
            every = classify_episode(cached, episode, config.distance)
            scores[e] = np.mean([np.argmax(p) == truth for (_, truth), p in zip(episode.queries, every)])
        out.append(scores)
    return out


def cells(scores: list[np.ndarray]) -> np.ndarray:
    """Each setting's accuracy in points (the mean over its episodes, as the evaluation's tables)."""
    return np.array([100 * s.mean() for s in scores])


def shape_shares(posterior: CachedPosterior) -> np.ndarray:
    classes = np.asarray(posterior.program.samples["class"], int)
    return np.bincount(classes, minlength=len(SHAPES)) / len(classes)


def median_shifts(a: dict, b: dict, properties=("scale", "colour", "specular", "shininess")) -> dict:
    """Per continuous property, how far the two runs' posterior medians of each image lie apart, in the draws' own
    standard deviations (pooled over both runs; log scale for the size; the largest over a property's coordinates):
    the median over images and the shares over 2 and over 5. Two runs of one posterior differ by a fraction of a
    standard deviation; a size posterior that settled on another pose lies several away."""
    out = {}
    for name in properties:
        z = []
        for i in sorted(a):
            x, y = (np.asarray(r[i].program.samples[name], np.float64) for r in (a, b))
            if name == "scale":
                x, y = np.log(x), np.log(y)
            sd = np.sqrt((x.var(axis=0) + y.var(axis=0)) / 2) + 1e-9
            z.append(float(np.max(np.abs(np.median(x, axis=0) - np.median(y, axis=0)) / sd)))
        z = np.array(z)
        out[name] = {"median": float(np.median(z)), "over_2": float(np.mean(z > 2)), "over_5": float(np.mean(z > 5))}
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("a", type=Path, help="evaluation run A")
    parser.add_argument("b", type=Path, help="evaluation run B (its posteriors and spread swapped into A's)")
    parser.add_argument("--moved", type=float, default=0.3,
                        help="an image's shape shares moved when one share differs by more than this")
    parser.add_argument("--spread", type=Path, action="append", default=[],
                        help="a concept spread file (spread-p3-N.json) to score A's posteriors with as well")
    args = parser.parse_args()
    dataset, config = load_dataset(args.dataset), EvaluationConfig()
    settings = test_settings(dataset, config.queries_per_class)
    names = [setting_name(n, k) for n, k in settings]
    a, spread_a = load_run(dataset, args.a, config)
    b, spread_b = load_run(dataset, args.b, config)
    calls = iter(range(1, 10 ** 6))

    def score(*args, **kwargs):       # a few minutes a whole scoring on 2 cores: say where it is
        print(f"scoring {next(calls)}...", file=sys.stderr, flush=True)
        return episode_scores(dataset, *args, settings=settings, config=config, **kwargs)

    scores = score(a, spread_a)
    base = cells(scores)
    rows = {"B": cells(score(b, spread_b)) - base}
    same_spread = (spread_a and spread_a.to_json()) == (spread_b and spread_b.to_json())
    rows["B's spread"] = np.zeros(len(settings)) if same_spread else cells(score(a, spread_b)) - base
    for path in args.spread:
        other_spread = ConceptSpread.from_json(json.loads(path.read_text()))
        rows[f"spread of {path.parent.name}"] = cells(score(a, other_spread)) - base
    moved = sorted(i for i in a if np.abs(shape_shares(a[i]) - shape_shares(b[i])).max() > args.moved)
    # with the same spread, B is already A with all of B's posteriors swapped in
    rows["B's posteriors"] = rows["B"] if same_spread else cells(score({**a, **b}, spread_a)) - base
    rows[f"{len(moved)} shape-moved images"] = (cells(score({**a, **{i: b[i] for i in moved}}, spread_a,
                                                            only=set(moved), base=scores)) - base
                                                if moved else np.zeros(len(settings)))
    rows["the other images"] = rows["B's posteriors"] - rows[f"{len(moved)} shape-moved images"]
    singles = {i: cells(score({**a, i: b[i]}, spread_a, only={i}, base=scores)) - base for i in moved}
    print(f"A ({args.a}): " + ", ".join(f"{name} {value:.1f}" for name, value in zip(names, base)))
    print(f"moves of the cells (points), B's part swapped into A:\n{'':34s}" + "".join(f"{n:>15s}" for n in names))
    for label, values in rows.items():
        print(f"{label[:34]:34s}" + "".join(f"{v:+15.1f}" for v in values))
    print(f"\nthe shape-moved images alone, shape shares ({'/'.join(SHAPES)}) and island gap A -> B:")
    for i in moved:
        print(f"{i:5d} {dataset.shots[i].class_name:30s} " + " ".join(f"{v:+5.1f}" for v in singles[i])
              + f"  {'/'.join(f'{p:.2f}' for p in shape_shares(a[i]))} -> "
              + f"{'/'.join(f'{p:.2f}' for p in shape_shares(b[i]))}"
              + f"  gap {a[i].island_gap:5.1f} -> {b[i].island_gap:5.1f}")
    shifts = median_shifts(a, b)
    print("\nposterior medians A against B, in the draws' standard deviations (median over images; shares over 2, 5):")
    for name, v in shifts.items():
        print(f"{name:10s} {v['median']:5.2f}  {v['over_2']:.2f}  {v['over_5']:.2f}")
    print(json.dumps({"cells": names, "a": base.tolist(), "moves": {k: v.tolist() for k, v in rows.items()},
                      "shape_moved_images": moved, "median_shifts": shifts}, indent=1))


if __name__ == "__main__":
    main()
