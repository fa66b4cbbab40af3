"""How much NP3's posteriors differ from P3's: an evaluation run's cached posteriors, image by image.

For every test image with both a P3 and an NP3 posterior in ``RUN`` (``mitsuba-p3
evaluate ... --likelihoods p3,np3``), prints JSON: the share of images whose
posterior draws are identical (the neural term then changed no decision of the
sampler), whose decided attributes differ (shape, material kind, size, colour, by
the model's attribute rules), and the median distance between the two posterior
mean positions (m).

    python experiments/compare_np3.py DATASET MODEL RUN
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate import CachedPosterior, posterior_path
from mitsuba_p3.evaluate.metrics import attribute_recovery
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel

ATTRIBUTES = ("shape", "material", "size", "colour")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("model", type=Path)
    parser.add_argument("run", type=Path)
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    rules = rules_for(FittedModel(args.model), dataset, learnt=False)
    both = [s for s in dataset.split("test")
            if all(posterior_path(args.run, k, s.index).exists() for k in ("p3", "np3"))]
    if not both:
        raise SystemExit(f"{args.run} has no test image with both a p3 and an np3 posterior")
    posteriors = {k: {s.index: CachedPosterior.load(posterior_path(args.run, k, s.index), 10 ** 6) for s in both}
                  for k in ("p3", "np3")}
    decided = {k: {row["query"]: row for row in attribute_recovery(dataset, posteriors[k], rules)[0]}
               for k in posteriors}
    identical, differs, distances = 0, {a: 0 for a in ATTRIBUTES}, []
    for shot in both:
        a, b = posteriors["p3"][shot.index], posteriors["np3"][shot.index]
        same = all(np.array_equal(a.program.samples[n], b.program.samples[n]) for n in a.program.samples)
        identical += same
        for name in ATTRIBUTES:
            key = f"{name}_decided"
            differs[name] += decided["p3"][shot.index][key] != decided["np3"][shot.index][key]
        distances.append(float(np.linalg.norm(np.asarray(a.shift) - np.asarray(b.shift))))
    accuracy = {k: {name: float(np.mean([r[f"{name}_decided"] == r[f"{name}_true"] for r in decided[k].values()]))
                    for name in ATTRIBUTES} for k in decided}
    print(json.dumps({"run": str(args.run), "images": len(both), "identical_draws": identical / len(both),
                      "attribute_differs": {k: v / len(both) for k, v in differs.items()},
                      "median_shift_distance_m": float(np.median(distances)), "accuracy": accuracy}, indent=2))


if __name__ == "__main__":
    main()
