"""Per test image of an evaluation run: each shape hypothesis's pooled log evidence, the posterior's shape
shares, the island gap and the seconds, one line per image, to compare two runs of one data set side by side.

    python experiments/demo_readings.py out/eval-small out/fsclvr-small

Columns: image index, log evidence (in :data:`mitsuba_p3.shapes.SHAPES` order), p (the draws' share of each
shape), the true shape, the island gap (nats) and the posterior's seconds.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.shapes import SHAPES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="an evaluation's --out folder (holds posteriors/p3/*.npz)")
    parser.add_argument("dataset", type=Path, help="its benchmark folder (labels.json)")
    args = parser.parse_args()
    labels = json.loads((args.dataset / "labels.json").read_text())["images"]
    paths = sorted((args.run / "posteriors" / "p3").glob("*.npz"))
    if not paths:
        raise SystemExit(f"{args.run} holds no P3 posteriors (posteriors/p3/*.npz)")
    for path in paths:
        with np.load(path) as d:
            index = int(path.stem)
            share = np.bincount(d["sample_class"].astype(int).ravel(), minlength=len(SHAPES)) / d["sample_class"].size
            print(index, "log Z", np.round(d["log_evidence"], 1), "p", share.round(3),
                  "truth", labels[index]["class"]["shape"], "gap", round(float(d["island_gap"]), 1),
                  "s", round(float(d["seconds"]), 1))


if __name__ == "__main__":
    main()
