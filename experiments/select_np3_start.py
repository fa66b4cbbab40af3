"""Where NP3's SMC should start, chosen on train images: from the prior, or from P3's posterior.

NP3's likelihood is P3's times a neural term, so its posterior can be reached two ways:
tempering the whole NP3 likelihood in from the prior (as P3's run does), or starting
from P3's final particles and tempering only the neural term in
(:func:`mitsuba_p3.infer.smc.bridge`). Both are exact SMC; they differ in cost and in
Monte Carlo error. For each of ``--images`` train images of a benchmark (spread evenly
over its train classes), this samples P3, NP3 bridged from P3's particles and NP3 from
the prior, one after another in one process (timings side by side), and prints a JSON
line per image and a summary: shape accuracy and mean log p(true shape) under each,
how often the two NP3 runs decide the same shape, the log evidences' mean difference,
and the seconds of each (the bridge's own, beside P3's and NP3-from-the-prior's).

    python experiments/select_np3_start.py data-lo/fsclvr data-lo/models/fsclvr --images 30 \\
        --out out/np3-start-fsclvr.jsonl

Resumes from ``--out`` (images already there are not sampled again).
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.posterior import default_likelihood, infer_image
from mitsuba_p3.infer.smc import SMCConfig
from mitsuba_p3.shapes import SHAPES


def train_images(dataset, count: int) -> list:
    """``count`` train shots, round robin over the train classes (first shot of each, then the second...)."""
    by_class: dict = {}
    for shot in dataset.split("train"):
        by_class.setdefault(shot.cls, []).append(shot)
    chosen, depth = [], 0
    while len(chosen) < count and any(depth < len(v) for v in by_class.values()):
        chosen += [v[depth] for v in by_class.values() if depth < len(v)]
        depth += 1
    return chosen[:count]


def hypotheses(posterior) -> dict:
    value = posterior.idata.posterior.attrs["hypotheses"]
    return json.loads(value) if isinstance(value, str) else value


def summarise(posterior, truth: str) -> dict:
    stats = hypotheses(posterior)
    weights = np.array([stats[s]["weight"] for s in SHAPES])
    return {"shape": SHAPES[int(np.argmax(weights))], "log_p_true": float(np.log(max(stats[truth]["weight"], 1e-300))),
            "log_evidence": [stats[s]["log_evidence"] for s in SHAPES],
            "seconds": float(posterior.idata.posterior.attrs["seconds"])}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("model", type=Path)
    parser.add_argument("--images", type=int, default=30)
    parser.add_argument("--out", type=Path, required=True, help="JSON lines, one per image (resumes)")
    args = parser.parse_args()

    dataset, fitted = load_dataset(args.dataset), FittedModel(args.model)
    config = SMCConfig()
    p3, np3 = (default_likelihood(fitted, kind, None, "fitted") for kind in ("p3", "np3"))
    done = {}
    if args.out.exists():
        done = {r["index"]: r for r in map(json.loads, args.out.read_text().splitlines())}
    args.out.parent.mkdir(parents=True, exist_ok=True)
    # one image first, unrecorded, so that no timing below includes a JIT compilation
    warm = train_images(dataset, 1)[0]
    infer_image(fitted, dataset.image(warm), np3, config,
                start=infer_image(fitted, dataset.image(warm), p3, config).particles)
    infer_image(fitted, dataset.image(warm), np3, replace(config, bridge=False))
    for shot in train_images(dataset, args.images):
        if shot.index in done:
            continue
        image, truth = dataset.image(shot), shot.cls.shape
        start = time.perf_counter()
        from_p3 = infer_image(fitted, image, p3, config)
        bridged = infer_image(fitted, image, np3, config, start=from_p3.particles)
        from_prior = infer_image(fitted, image, np3, replace(config, bridge=False))
        row = {"index": shot.index, "truth": truth, "p3": summarise(from_p3, truth),
               "bridged": summarise(bridged, truth), "prior": summarise(from_prior, truth),
               "wall_seconds": time.perf_counter() - start}
        with args.out.open("a") as f:
            f.write(json.dumps(row) + "\n")
        done[shot.index] = row
        print(json.dumps(row), flush=True)
    rows = list(done.values())
    summary = {"images": len(rows)}
    for name in ("p3", "bridged", "prior"):
        summary[name] = {"shape_accuracy": float(np.mean([r[name]["shape"] == r["truth"] for r in rows])),
                         "mean_log_p_true": float(np.mean([r[name]["log_p_true"] for r in rows])),
                         "mean_seconds": float(np.mean([r[name]["seconds"] for r in rows]))}
    summary["same_shape_bridged_prior"] = float(np.mean([r["bridged"]["shape"] == r["prior"]["shape"] for r in rows]))
    difference = np.array([np.subtract(r["bridged"]["log_evidence"], r["prior"]["log_evidence"]) for r in rows])
    summary["log_evidence_bridged_minus_prior"] = {"median": float(np.median(difference)),
                                                   "median_abs": float(np.median(np.abs(difference)))}
    summary["cost_np3_over_p3"] = {"bridged": summary["bridged"]["mean_seconds"] / summary["p3"]["mean_seconds"],
                                   "prior": summary["prior"]["mean_seconds"] / summary["p3"]["mean_seconds"]}
    print(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
