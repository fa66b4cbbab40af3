"""Choose the protoprogram distance's terms on a benchmark's *train* classes.

Re-scores the cached train-class posteriors of ``experiments/select_sigma.py`` (one
sigma's folder, 2+ shots per class) on N-way 1-shot episodes among the train
classes, with the distance restricted to each given subset of properties. No
test image is used, so the chosen subset can then be evaluated on the test
split (``experiments/ablate_distance.py --subsets``) without peeking.

    python experiments/select_distance.py data/fsclvr results/sigma/fsclvr/sigma-1 \\
        [--subsets all,colour,colour+class,colour+scale+class] [--episodes 200]
"""
from __future__ import annotations

import argparse
from pathlib import Path

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.concepts import DistanceConfig, parse_properties
from mitsuba_p3.errors import MitsubaP3Error
from mitsuba_p3.evaluate import held_out_accuracy, markdown_table
from mitsuba_p3.evaluate.jobs import cached_train_programs

WAYS = (5, 10)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path, help="a select_sigma.py folder, e.g. results/sigma/fsclvr/sigma-1")
    parser.add_argument("--subsets", default="all,colour,colour+class,colour+scale+class,"
                                             "scale+colour+ambient+diffuse+class")
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    try:
        subsets = [(s, parse_properties(s)) for s in args.subsets.split(",")]
    except MitsubaP3Error as error:
        parser.error(str(error))
    dataset = load_dataset(args.dataset)
    programs = cached_train_programs(dataset, args.run, args.likelihood, DistanceConfig.max_points)
    if min(len(v) for v in programs.values()) < 2:
        parser.error(f"{args.run} needs at least 2 cached posteriors of every train class (select_sigma.py)")
    rows = []
    for label, properties in subsets:
        config = DistanceConfig(properties=properties)
        cells = [f"{100 * held_out_accuracy(programs, n, args.episodes, args.seed, config):.1f}"
                 for n in WAYS]
        rows.append([label] + cells)
        print(f"{label}: {' / '.join(cells)}", flush=True)
    print()
    print(markdown_table(["distance terms"] + [f"{n}-way 1-shot (train classes)" for n in WAYS], rows))


if __name__ == "__main__":
    main()
