"""Two ``mitsuba-p3 evaluate`` runs of one data set, paired episode by episode.

Two evaluations of the same data set share their episodes (a pure function of the data set and the
evaluation's seed), so a difference between them is paired: per episode, B's accuracy minus A's. This
prints for every few-shot setting both accuracies and the paired difference with its 95% bootstrap
interval over episodes (a cell that moved by less than that interval moved by sampling alone), and
both runs' attribute accuracies, and, where both keep their posteriors (``posteriors/MODEL/*.npz``), how
far the posteriors of the images both sampled agree: the share whose modal shape is the same, those whose
shape shares moved by more than 0.3, each run's island gap (median, 90th percentile, share over 10 nats),
its temperatures and seconds per posterior (``--posteriors-only``: that alone, for a run still sampling). It
refuses two runs whose episodes differ (another data set, another episode seed):

    python scripts/compare_evaluations.py results/eval-fsclvr-s1 results/eval-fsclvr-tinted [--model p3]
"""
from __future__ import annotations

import argparse
import csv
import json
import sys
from pathlib import Path

import numpy as np

from mitsuba_p3.shapes import SHAPES

ATTRIBUTES = ("shape", "material", "size", "colour")


def read_rows(path: Path, model: str) -> list[dict]:
    with open(path, newline="") as handle:
        return [r for r in csv.DictReader(handle) if r["model"] == model]


def per_episode(rows: list[dict]) -> dict[tuple, dict[int, list]]:
    """(n_way, k_shot) -> episode -> its predictions' (query, truth, right) in file order."""
    out: dict[tuple, dict[int, list]] = {}
    for r in rows:
        setting = (int(r["n_way"]), int(r["k_shot"]))
        out.setdefault(setting, {}).setdefault(int(r["episode"]), []).append(
            (r["query"], r["truth"], r["predicted"] == r["truth"]))
    return out


def paired_difference(a: dict[int, list], b: dict[int, list], draws: int = 10000, seed: int = 0) -> tuple:
    """Mean accuracies (points) of A and B, and B - A with its 95% bootstrap interval over episodes."""
    episodes = sorted(a)
    acc_a = np.array([np.mean([right for *_, right in a[e]]) for e in episodes])
    acc_b = np.array([np.mean([right for *_, right in b[e]]) for e in episodes])
    diff = acc_b - acc_a
    rng = np.random.default_rng(seed)
    boot = diff[rng.integers(len(diff), size=(draws, len(diff)))].mean(axis=1)
    low, high = np.percentile(boot, [2.5, 97.5])
    return 100 * acc_a.mean(), 100 * acc_b.mean(), 100 * diff.mean(), 100 * low, 100 * high


def attribute_accuracy(path: Path, model: str) -> dict[str, float]:
    rows = read_rows(path, model)
    return {a: 100 * float(np.mean([r[f"{a}_true"] == r[f"{a}_decided"] for r in rows])) for a in ATTRIBUTES}


def posterior_agreement(a: Path, b: Path, model: str) -> list[str] | None:
    """Lines on the cached posteriors both runs hold (module docstring); None where they share none."""
    folders = [run / "posteriors" / model for run in (a, b)]
    images = sorted(set.intersection(*({p.stem for p in folder.glob("*.npz")} for folder in folders)))
    if not images:
        return None
    cached = [[np.load(folder / f"{image}.npz") for image in images] for folder in folders]

    def shares(posterior) -> np.ndarray:
        classes = np.asarray(posterior["sample_class"], int)
        return np.bincount(classes, minlength=len(SHAPES)) / len(classes)

    pairs = [(shares(x), shares(y)) for x, y in zip(*cached)]
    agree = np.mean([x.argmax() == y.argmax() for x, y in pairs])
    moved = [int(image) for image, (x, y) in zip(images, pairs) if np.abs(x - y).max() > 0.3]
    lines = [f"posteriors of {len(images)} images: modal shape the same in {100 * agree:.1f}%, shape shares moved by "
             f"> 0.3 on {len(moved)}: {moved}"]
    for name, run in zip("AB", cached):
        gaps = np.array([float(p["island_gap"]) for p in run])
        lines.append(f"{name}: island gap median {np.median(gaps):.2f}, p90 {np.quantile(gaps, 0.9):.1f}, > 10 nats "
                     f"{100 * np.mean(gaps > 10):.0f}%; temperatures median "
                     f"{np.median([int(p['particles_temperatures']) for p in run]):.0f}; seconds per posterior mean "
                     f"{np.mean([float(p['seconds']) for p in run]):.1f}")
    return lines


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("a", type=Path, help="the first evaluation's output folder (its predictions.csv)")
    parser.add_argument("b", type=Path, help="the second")
    parser.add_argument("--model", default="p3")
    parser.add_argument("--posteriors-only", action="store_true",
                        help="compare only the cached posteriors both hold (runs still sampling have no episodes yet)")
    args = parser.parse_args(argv)
    if args.posteriors_only:
        print("\n".join(posterior_agreement(args.a, args.b, args.model) or ["no cached posteriors in common"]))
        return
    labels = [json.loads((folder / "run.json").read_text()).get("labels_digest") for folder in (args.a, args.b)]
    if labels[0] != labels[1]:
        sys.exit("error: the two runs evaluated different data sets (their run.json's labels_digest differ): "
                 "they cannot be paired")
    runs = [per_episode(read_rows(folder / "predictions.csv", args.model)) for folder in (args.a, args.b)]
    for setting in sorted(runs[0].keys() & runs[1].keys()):
        a, b = runs[0][setting], runs[1][setting]
        same = a.keys() == b.keys() and all([q[:2] for q in a[e]] == [q[:2] for q in b[e]] for e in a)
        if not same:
            sys.exit(f"error: the two runs' {setting[0]}-way {setting[1]}-shot episodes differ (another data set or "
                     "episode seed): they cannot be paired")
        acc_a, acc_b, diff, low, high = paired_difference(a, b)
        print(f"{setting[0]}-way {setting[1]}-shot: {acc_a:5.1f} -> {acc_b:5.1f}, paired difference {diff:+.1f} "
              f"[{low:+.1f}, {high:+.1f}] over {len(a)} episodes")
    attrs = [attribute_accuracy(folder / "attributes.csv", args.model) for folder in (args.a, args.b)]
    print("attributes (A -> B): " + ", ".join(f"{k} {attrs[0][k]:.1f} -> {attrs[1][k]:.1f}" for k in ATTRIBUTES))
    for line in posterior_agreement(args.a, args.b, args.model) or []:
        print(line)


if __name__ == "__main__":
    main()
