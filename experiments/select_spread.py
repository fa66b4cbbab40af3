"""Should protoprograms carry a concept spread? Decided on a benchmark's *train* classes, cross-fitted.

Loads cached posteriors of train images (``mitsuba-p3 evaluate`` writes them to
``RUN/posteriors/LIKELIHOOD`` when it fits a spread, or any run over train shots),
splits the train classes into two halves, fits the
:class:`~mitsuba_p3.concepts.ConceptSpread` on one half and scores seeded N-way
K-shot episodes among the other half's classes, then the other way round. Each
distance is scored with the paper's programs (no spread) and with the fitted
spread, so the spread is judged on classes it was not fitted on; ``--directions``
adds the KL's other direction. No test image is used. K-shot episodes need K + 1
posteriors per train class (``evaluate`` samples three; ``experiments/sample_train_shots.py``
samples six, for 5-shot episodes).

    python experiments/select_spread.py data/fsclvr out/eval-fitted [--likelihood p3] [--episodes 200]
        [--subsets all,colour+class] [--shots 1,5] [--directions class||image,image||class] [--spreads fitted]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.concepts import DistanceConfig, fit_spread, parse_properties
from mitsuba_p3.errors import MitsubaP3Error
from mitsuba_p3.evaluate import held_out_accuracy, markdown_table
from mitsuba_p3.evaluate.jobs import cached_train_programs
from mitsuba_p3.evaluate.run import train_shapes

WAYS = (5, 10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path, help="a run folder holding posteriors of train images")
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--subsets", default="all,colour+class")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--shots", default="1", help="K of the K-shot episodes, e.g. 1,5")
    parser.add_argument("--directions", default=DistanceConfig.direction,
                        help="KL directions, e.g. class||image,image||class (the paper's first)")
    parser.add_argument("--spreads", default="none,fitted", help="none (the paper's programs), fitted, or both")
    args = parser.parse_args()
    try:
        subsets = [(s, parse_properties(s)) for s in args.subsets.split(",")]
        configs = [(label, direction, DistanceConfig(properties=properties, direction=direction))
                   for label, properties in subsets for direction in args.directions.split(",")]
    except MitsubaP3Error as error:
        parser.error(str(error))
    shots = [int(k) for k in args.shots.split(",")]
    if not set(args.spreads.split(",")) <= {"none", "fitted"}:
        parser.error(f"--spreads: choose none, fitted or none,fitted; got {args.spreads!r}")
    dataset = load_dataset(args.dataset)
    programs = {name: found for name, found in
                cached_train_programs(dataset, args.run, args.likelihood, DistanceConfig.max_points).items()
                if len(found) >= max(shots) + 1}
    names = sorted(programs)
    half = len(names) // 2
    if half < max(WAYS):
        parser.error(f"{args.run} has {max(shots) + 1}+ train posteriors for {len(names)} classes; "
                     f"cross-fitting {max(WAYS)}-way episodes needs {2 * max(WAYS)}")
    order = np.random.default_rng(args.seed).permutation(names)
    folds = [list(order[:half]), list(order[half:])]
    shapes = train_shapes(dataset)
    spreads = [fit_spread({c: programs[c] for c in folds[1 - f]}, shapes) for f in range(2)]
    for f, spread in enumerate(spreads):
        print(f"spread fitted on fold {1 - f} ({spread.images} images, {spread.classes} classes): class error "
              f"{spread.class_error:.3f}; sd " + ", ".join(
                  f"{k} {np.sqrt(np.diag(v)).round(4).tolist()}" for k, v in spread.covariance.items()), flush=True)
    settings = [(n_way, k_shot) for n_way in WAYS for k_shot in shots]
    # each fold's programs under each spread, built once (their KDEs are cached on them)
    scored = {name: [{c: [p.with_spread(spreads[f] if name == "fitted" else None) for p in programs[c]]
                      for c in fold} for f, fold in enumerate(folds)] for name in args.spreads.split(",")}
    rows, report = [], {}
    for label, direction, config in configs:
        for spread_name, by_fold in scored.items():
            cells = [100 * float(np.mean([held_out_accuracy(fold, n_way, args.episodes, args.seed, config, k_shot)
                                          for fold in by_fold])) for n_way, k_shot in settings]
            report[f"{label}/{direction}/{spread_name}"] = cells
            rows.append([label, direction, spread_name] + [f"{c:.1f}" for c in cells])
            print(f"{label} {direction} spread {spread_name}: {' / '.join(rows[-1][3:])}", flush=True)
    print()
    print(markdown_table(["distance terms", "KL", "spread"]
                         + [f"{n}-way {k}-shot (held-out train classes)" for n, k in settings], rows))
    print(json.dumps(report))


if __name__ == "__main__":
    main()
