"""Which object properties does few-shot classification rely on? A distance ablation.

Re-scores an evaluation run's cached posteriors (``mitsuba-p3 evaluate`` made
them; nothing is resampled) with the protoprogram distance restricted to
property subsets: all of them (the paper's distance), all but one, and one
alone. Prints a markdown table of accuracies on the run's own episodes.

    python experiments/ablate_distance.py data/fsclvr results/runs/fsclvr [--likelihood p3] [--episodes 100]
        [--subsets colour+class,colour] [--spread-shots 0]
"""
from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.concepts import PROPERTIES, DistanceConfig, parse_properties
from mitsuba_p3.errors import MitsubaP3Error
from mitsuba_p3.evaluate import (CachedPosterior, EvaluationConfig, classify_episodes, markdown_table,
                                 posterior_path, setting_name)
from mitsuba_p3.evaluate.metrics import test_settings
from mitsuba_p3.evaluate.run import run_spread


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--subsets", default=None,
                        help="only these subsets, e.g. colour+class,colour (default: all, all but one, one alone)")
    parser.add_argument("--spread-shots", type=int, default=DistanceConfig.spread_shots,
                        help="train images per class that fit the concept spread (0: the paper's programs)")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    try:
        distance = DistanceConfig(spread_shots=args.spread_shots)
        spread = run_spread(dataset, args.run, args.likelihood, EvaluationConfig(distance=distance))
    except (MitsubaP3Error, FileNotFoundError) as error:
        parser.error(f"{error} (the run needs posteriors of {args.spread_shots} train images per class, "
                     "or --spread-shots 0)")
    cached = {}
    for shot in dataset.split("test"):
        post = CachedPosterior.load(posterior_path(args.run, args.likelihood, shot.index), distance.max_points)
        cached[shot.index] = replace(post, program=post.program.with_spread(spread))
    if args.subsets:
        try:
            subsets = [(subset, parse_properties(subset)) for subset in args.subsets.split(",")]
        except MitsubaP3Error as error:
            parser.error(str(error))
    else:
        subsets = [("all (paper)", PROPERTIES)]
        subsets += [(f"all but {p}", tuple(q for q in PROPERTIES if q != p)) for p in PROPERTIES]
        subsets += [(f"{p} only", (p,)) for p in PROPERTIES]
    settings = test_settings(dataset)
    rows = []
    for label, properties in subsets:
        config = EvaluationConfig(episodes=args.episodes, distance=replace(distance, properties=properties))
        cells = []
        for n_way, k_shot in settings:
            predictions = classify_episodes(dataset, cached, n_way, k_shot, config)
            cells.append(f"{100 * np.mean([r['predicted'] == r['truth'] for r in predictions]):.1f}")
        rows.append([label] + cells)
        print(f"{label}: {' / '.join(cells)}", flush=True)
    print()
    print(markdown_table(["distance terms"] + [setting_name(n, k) for n, k in settings], rows))


if __name__ == "__main__":
    main()
