"""How much of its colour's saturation does each posterior keep? Per class and size, train and test.

For every cached posterior of an evaluation run whose class has a chromatic colour (gray left out), the
*saturation kept*: the projection of the posterior's median chromaticity, from gray (1/3, 1/3, 1/3), onto
the direction of its colour and kind's centre in the model's rule (:func:`~mitsuba_p3.fit.attributes.rules_for`:
the centres learnt from the material's posterior at train images' true poses), as a fraction of that centre's
distance from gray. 1: as saturated as the material at the true pose; below 1: washed out towards gray, along
the line a gray offset moves it; above 1: more saturated. Prints the 10th, 50th and 90th percentiles per
split, size and kind, then per class the median and how many of its posteriors that rule names right.

    python experiments/probe_saturation.py data/dark-lo out/eval-dark-white data/models/dark-white

Written for dark's colour regression (thirty-first session: achromatic shading fields on a flat face trade
the colour's saturation for a gray offset; ``results/fields-tinted``).
"""
from __future__ import annotations

import argparse
import collections
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import CachedPosterior, posterior_path
from mitsuba_p3.fit.attributes import median_chromaticity, rules_for
from mitsuba_p3.fit.model import FittedModel

GRAY = np.full(3, 1.0 / 3.0)


def saturation_kept(chromaticity: np.ndarray, centre: np.ndarray) -> float:
    """The projection of ``chromaticity - gray`` on ``centre - gray``, over the latter's length squared."""
    direction = np.asarray(centre) - GRAY
    return float(np.dot(np.asarray(chromaticity) - GRAY, direction) / np.dot(direction, direction))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("run", help="an evaluation run folder (its cached posteriors)")
    parser.add_argument("model")
    parser.add_argument("--likelihood", default="p3")
    args = parser.parse_args()
    dataset, run = load_dataset(args.dataset), Path(args.run)
    rules = rules_for(FittedModel(args.model), dataset)
    centres = {(name, kind): centre for name, kind, centre in
               zip(rules.colour_names, rules.colour_kinds, rules.colour_albedos)}
    labels = dataset.class_labels
    groups, classes = collections.defaultdict(list), collections.defaultdict(list)
    for split in ("train", "test"):
        for shot in dataset.split(split):
            path = posterior_path(run, args.likelihood, shot.index)
            label = labels[shot.cls.name]
            key = (label.colour, label.material)
            if not path.exists() or key not in centres or label.colour == "gray":
                continue
            chromaticity = median_chromaticity(CachedPosterior.load(path, 400).program.samples)
            kept = saturation_kept(chromaticity, centres[key])
            groups[(split, label.size, label.material)].append(kept)
            classes[(split, shot.cls.name)].append((kept, rules.colour_name(chromaticity) == label.colour))
    for key in sorted(groups):
        print(*key, len(groups[key]), np.round(np.quantile(groups[key], [0.1, 0.5, 0.9]), 2).tolist())
    for (split, name), rows in sorted(classes.items()):
        print(split, name, round(float(np.median([r[0] for r in rows])), 2),
              f"{sum(r[1] for r in rows)}/{len(rows)} named right")


if __name__ == "__main__":
    main()
