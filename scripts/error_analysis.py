"""Which class attributes P3/NP3 confuse: a run's misclassifications, grouped.

A benchmark class is (shape, colour, material, size). For every wrong
prediction in ``RUN/predictions.csv`` this lists the attributes in which the
true and the predicted class differ, and the most frequent (true -> predicted)
pairs, so one sees at a glance whether errors come from shape, colour or
material. It then splits the attribute recovery of ``RUN/attributes.csv`` (what each test
posterior names) by the object's true size: on 120x160 images a small object covers a few
dozen pixels. Last, for an SMC run, how far each image's two (or more) runs of the true shape's
hypothesis disagree about its log evidence (the *island gap*, from the cached posteriors): the
Monte Carlo error of the evidence that decides the shape, beside the error that tempering alone
would leave (about sqrt(T / N) nats for T temperatures of N particles), split into the train
images (those the concept spread was fitted on) and the test images. The episodes are re-drawn
from the data set as evaluation draws them by default (seed 0, one query per class), and every
query is checked against them.

    python scripts/error_analysis.py data/fsclvr results/runs/fsclvr [--likelihood p3] [--top 15]
"""
from __future__ import annotations

import argparse
import collections
import csv
import json
from pathlib import Path

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.benchmarks.episodes import sample_episodes
from mitsuba_p3.evaluate import EvaluationConfig

ATTRIBUTES = ("shape", "colour", "material", "size")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--top", type=int, default=15)
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    labels = dataset.class_labels
    results = json.loads((args.run / "results.json").read_text())["results"][args.likelihood]
    rows = [r for r in csv.DictReader(open(args.run / "predictions.csv")) if r["model"] == args.likelihood]
    if not rows:
        parser.error(f"{args.run / 'predictions.csv'} has no predictions of likelihood {args.likelihood!r}")
    episodes_per_setting = next(iter(results["accuracy"].values()))["episodes"]
    defaults = EvaluationConfig()
    episodes, by_attributes, pairs, total = {}, collections.Counter(), collections.Counter(), 0
    for row in rows:
        key = int(row["n_way"]), int(row["k_shot"])
        if key not in episodes:
            episodes[key] = sample_episodes(dataset, *key, episodes_per_setting, defaults.episode_seed,
                                            defaults.queries_per_class)
        episode = episodes[key][int(row["episode"])]
        truth, predicted = episode.classes[int(row["truth"])], episode.classes[int(row["predicted"])]
        if dataset.shots[int(row["query"])].cls.name != truth:
            parser.error(f"{args.run} was not scored on {args.dataset}'s default episodes (query {row['query']})")
        total += 1
        if truth != predicted:
            differ = [a for a in ATTRIBUTES if getattr(labels[truth], a) != getattr(labels[predicted], a)]
            by_attributes["+".join(differ)] += 1
            pairs[(truth, predicted)] += 1
    wrong = sum(by_attributes.values())
    print(f"{args.run} ({args.likelihood}): {wrong} of {total} predictions wrong, all settings together\n")
    print("| true and predicted class differ in | errors | share |\n|---|---|---|")
    for differ, count in by_attributes.most_common():
        print(f"| {differ} | {count} | {100 * count / wrong:.0f}% |")
    print("\n| true class | predicted class | errors |\n|---|---|---|")
    for (truth, predicted), count in pairs.most_common(args.top):
        print(f"| {truth} | {predicted} | {count} |")
    recovered = [r for r in csv.DictReader(open(args.run / "attributes.csv")) if r["model"] == args.likelihood] \
        if (args.run / "attributes.csv").is_file() else []
    if recovered:
        print("\n| true size | images | " + " | ".join(f"{a} right" for a in ATTRIBUTES) + " |\n|---|---|"
              + "---|" * len(ATTRIBUTES))
        for size in sorted({r["size_true"] for r in recovered}):
            these = [r for r in recovered if r["size_true"] == size]
            right = [100 * sum(r[f"{a}_true"] == r[f"{a}_decided"] for r in these) / len(these) for a in ATTRIBUTES]
            print(f"| {size} | {len(these)} | " + " | ".join(f"{v:.1f}%" for v in right) + " |")
    island_gaps(dataset, args.run / "posteriors" / args.likelihood)


def island_gaps(dataset, cache: Path) -> None:
    """The island gap of the true shape's hypothesis per cached SMC posterior, train and test images apart."""
    import numpy as np

    from mitsuba_p3.shapes import SHAPES

    by_split = collections.defaultdict(lambda: collections.defaultdict(list))
    for file in sorted(cache.glob("*.npz")):
        posterior = np.load(file)
        if "particles_log_evidence" not in posterior.files:
            continue                                    # an MH posterior: no runs to compare
        shot = dataset.shots[int(file.stem)]
        if shot.cls.shape not in SHAPES:
            continue                                    # ood: no true primitive
        index, evidence = posterior["particles_index"], posterior["particles_log_evidence"]
        mine = evidence[index == SHAPES.index(shot.cls.shape)]
        if len(mine) < 2:
            continue
        row = by_split[shot.split]
        row["gap"].append(float(np.ptp(mine)))
        particles = posterior["particles_position"].shape[1]
        row["tempering"].append(float(np.sqrt(posterior["particles_temperatures"] / particles)))
        row["right"].append(int(posterior["kappa"]) == SHAPES.index(shot.cls.shape))     # the decided shape
    if not by_split:
        return
    print("\n| images | runs' log evidence of the true shape: gap median / p90 (nats) | gap > 10 nats "
          "| sqrt(T / N), median | shape wrong, gap <= 10 / > 10 |\n|---|---|---|---|---|")
    for split, row in sorted(by_split.items()):
        gap, right = np.array(row["gap"]), np.array(row["right"])
        wrong = [f"{100 * np.mean(~right[m]):.1f}%" if m.any() else "-" for m in (gap <= 10, gap > 10)]
        print(f"| {split} ({len(gap)}) | {np.median(gap):.1f} / {np.percentile(gap, 90):.1f} | "
              f"{100 * np.mean(gap > 10):.1f}% | {np.median(row['tempering']):.2f} | {' / '.join(wrong)} |")


if __name__ == "__main__":
    main()
