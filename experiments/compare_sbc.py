"""Two or more SBC runs of one model, side by side on the simulations they share.

``mitsuba-p3 sbc`` seeds simulation i by (seed, i), so runs of different sampler settings with
the same seed and model see the same scenes and images: their first n simulations compare
pair for pair. For each run (a folder with ``cache.npz``) this prints, over the first n
simulations of all of them, per checked coordinate the KS p-value of the ranks, the share of
simulations whose truth lies outside all draws (ranks 0 or L; 2 / (L + 1) for a calibrated
sampler), and the shape posterior's accuracy and ECE. Used for the gradient move
(docs/notebook.md, "A gradient move over the pose"):

    python experiments/compare_sbc.py default=results/sbc-fsclvr final3=out/sbc-mala/final3 ...

``--start k`` compares simulations k.. only: a run resumed on another machine's fit of the model
compares pair for pair only over what both made on the same fit.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.evaluate.sbc import CHECKED, SBCResult


def load(folder: Path) -> SBCResult:
    with np.load(folder / "cache.npz") as f:
        return SBCResult(f["ranks"], int(f["draws"]), f["probabilities"], f["truths"])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("runs", nargs="+", help="NAME=FOLDER, each holding an SBC cache.npz")
    parser.add_argument("--images", type=int, help="the first n simulations (default: as many as all runs hold)")
    parser.add_argument("--start", type=int, default=0,
                        help="leave out the simulations before this one (e.g. those a run made on another fit)")
    args = parser.parse_args()
    runs = {name: load(Path(folder)) for name, folder in (r.split("=", 1) for r in args.runs)}
    n = min(len(r.ranks) for r in runs.values())
    n = min(n, args.images or n)
    report = {"images": n - args.start, "simulations": [args.start, n]}
    for name, run in runs.items():
        part = slice(args.start, n)
        cut = SBCResult(run.ranks[part], run.draws, run.class_probabilities[part], run.true_class[part])
        summary = cut.summary()
        extreme = np.mean((cut.ranks == 0) | (cut.ranks == cut.draws), axis=0)
        report[name] = {"ks_p": {c: round(summary["rank_uniformity_ks_p"][c], 5) for c in CHECKED},
                        "outside_all_draws": {c: round(float(v), 3) for c, v in zip(CHECKED, extreme)},
                        "shape_accuracy": summary["class"]["accuracy"], "shape_ece": round(summary["class"]["ece"], 4)}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
