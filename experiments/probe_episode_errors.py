"""Which few-shot confusions come from misread attributes, and which from the distance itself.

For each of an evaluation's settings, takes every wrong episode prediction and asks (from the run's
``attributes.csv``, the rules' named attributes) whether the query and its true class's support shots
were each read right in every attribute. A confusion where both were read right is the distance's
doing (the programs' continuous terms placed the query nearer another class), not the posterior's;
the others would fall with better readings. Prints, per setting, the errors by which attributes the
true and predicted classes differ in and by (query read right, support read right), and for 10-way
1-shot the most frequent confusions among images all read right. Reads only the run's tables.

    python experiments/probe_episode_errors.py data/dark-lo out/eval-dark-tinted
"""
from __future__ import annotations

import argparse
import collections
import csv
import json
from pathlib import Path

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.benchmarks.episodes import sample_episodes
from mitsuba_p3.evaluate.config import EvaluationConfig
from mitsuba_p3.files import file_digest

ATTRIBUTES = ("size", "colour", "material", "shape")          # the order of a class name's words


def read_right(row: dict) -> bool:
    return all(row[f"{a}_true"] == row[f"{a}_decided"] for a in ATTRIBUTES)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path, help="an evaluation run (its predictions.csv and attributes.csv)")
    parser.add_argument("--model", default="p3")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    if json.loads((args.run / "run.json").read_text()).get("labels_digest") != file_digest(args.dataset / "labels.json"):
        raise SystemExit(f"error: {args.run} did not evaluate {args.dataset} (its run.json's labels digest differs)")
    config = EvaluationConfig()
    with open(args.run / "predictions.csv", newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r["model"] == args.model]
    with open(args.run / "attributes.csv", newline="") as handle:
        right = {int(r["query"]): read_right(r) for r in csv.DictReader(handle) if r["model"] == args.model}
    for n_way, k_shot in sorted({(int(r["n_way"]), int(r["k_shot"])) for r in rows}):
        episodes = sample_episodes(dataset, n_way, k_shot, config.episodes, config.episode_seed,
                                   config.queries_per_class)
        differ, readings, pairs, total = collections.Counter(), collections.Counter(), collections.Counter(), 0
        for r in rows:
            if (int(r["n_way"]), int(r["k_shot"])) != (n_way, k_shot):
                continue
            total += 1
            if r["predicted"] == r["truth"]:
                continue
            episode = episodes[int(r["episode"])] if int(r["episode"]) < len(episodes) else None
            if episode is None or (int(r["query"]), int(r["truth"])) not in episode.queries:
                raise SystemExit(f"error: {args.run}'s episodes are not the default evaluation's (another --episodes "
                                 "or episode seed); this probe redraws the defaults")
            truth, predicted = episode.classes[int(r["truth"])], episode.classes[int(r["predicted"])]
            differ["+".join(a for a, x, y in zip(ATTRIBUTES, truth.split("-"), predicted.split("-")) if x != y)] += 1
            reading = (right[int(r["query"])], all(right[s] for s in episode.support[int(r["truth"])]))
            readings[reading] += 1
            if all(reading):
                pairs[(truth, predicted)] += 1
        wrong = sum(differ.values())
        print(f"{n_way}-way {k_shot}-shot: {wrong} of {total} wrong; the classes differ in "
              + ", ".join(f"{k} {v}" for k, v in differ.most_common())
              + "; (query, support) read right: " + ", ".join(f"{k} {v}" for k, v in sorted(readings.items())))
        if (n_way, k_shot) == (10, 1):
            for (truth, predicted), count in pairs.most_common(6):
                print(f"    all read right, {count} x {truth} -> {predicted}")


if __name__ == "__main__":
    main()
