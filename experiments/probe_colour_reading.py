"""How a posterior's colour is read: the colour centres of the fit's rule and of the rule evaluate learns from
train posteriors, beside the median chromaticity of chosen classes' test posteriors and the name each rule gives.

    python experiments/probe_colour_reading.py data/dark-lo out/eval-dark-white data/models/dark-white \\
        [--classes small-green-rubber-cube,small-brown-rubber-cylinder]

Written for dark's colour regression (thirtieth session, results/eval-dark-white).
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.config import EvaluationConfig
from mitsuba_p3.evaluate.jobs import CachedPosterior, PosteriorMisfits, posterior_path
from mitsuba_p3.evaluate.run import rules_with_train_posteriors
from mitsuba_p3.fit.attributes import median_chromaticity, rules_for
from mitsuba_p3.fit.model import FittedModel


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("run", help="an evaluation run folder (its cached test and train posteriors)")
    parser.add_argument("model")
    parser.add_argument("--classes", default="small-green-rubber-cube,small-brown-rubber-cylinder")
    args = parser.parse_args()
    dataset, run, model = load_dataset(args.dataset), Path(args.run), Path(args.model)
    fit = rules_for(FittedModel(model), dataset)
    learnt = rules_with_train_posteriors(fit, dataset, run, "p3", PosteriorMisfits(dataset, model))
    for name, rules in (("fit's rule", fit), ("learnt from train posteriors", learnt)):
        kinds = rules.colour_kinds or [None] * len(rules.colour_names)
        print(name, [(colour, kind, np.round(centre, 3).tolist())
                     for colour, kind, centre in zip(rules.colour_names, kinds, rules.colour_albedos)])
    max_points = EvaluationConfig().distance.max_points
    chosen = set(args.classes.split(","))
    for shot in dataset.split("test"):
        if shot.cls.name in chosen:
            post = CachedPosterior.load(posterior_path(run, "p3", shot.index), max_points)
            chromaticity = median_chromaticity(post.program.samples)
            print(shot.index, shot.cls.name, np.round(chromaticity, 3).tolist(), fit.colour_name(chromaticity),
                  learnt.colour_name(chromaticity))


if __name__ == "__main__":
    main()
