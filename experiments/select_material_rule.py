"""Which material-kind rule? Compared on *train* posteriors, leave one class out.

The material kind (rubber or metal) of a posterior is decided by a logistic
regression on the posterior medians of the Phong weights (k_a, k_d, k_s, log alpha).
Two ways to learn it, compared here on the cached train posteriors of an
evaluation run (``mitsuba-p3 evaluate`` caches them for the concept spread):

- ``fit``: learnt from the materials the fit optimised per train colour and kind
  (``materials.json``; 16 points), the rule ``mitsuba-p3 infer`` uses (one image has no
  train posteriors beside it);
- ``posteriors``: learnt from the train posteriors themselves, whose kinds the labels
  give, so the classifier sees at training the kind of input it is applied to; the rule
  ``mitsuba-p3 evaluate`` uses, since its runs hold train posteriors for the concept spread;
- ``posteriors+saturation``: the same with the saturation of the posterior's median
  reflectance as a fifth feature;
- ``posteriors+saturation+misfit``: and the log of the posterior's Phong misfit as a sixth
  (:mod:`mitsuba_p3.infer.misfit`: how much of the object the best Phong render at the
  posterior's pose leaves unexplained, in units of the fitted noise).

Each train class is held out in turn: the ``posteriors`` rule is learnt on the other
classes' posteriors and scored on the held-out class's (the ``fit`` rule is fixed).
Prints JSON: material accuracy per rule, and how many posteriors were scored.

    python experiments/select_material_rule.py --dataset data/fsclvr-lo --model data/models/fsclvr-lo \\
        --run out/train-smc-v5 [--likelihood p3]
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import PosteriorMisfits, cached_train_posteriors, rules_learnt_from
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel

FEATURES = {"posteriors": "weights", "posteriors+saturation": "weights+saturation",
            "posteriors+saturation+misfit": "weights+saturation+misfit"}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--run", required=True, help="an evaluation run with cached train posteriors")
    parser.add_argument("--likelihood", default="p3")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    fit_rules = rules_for(FittedModel(args.model), dataset, learnt=False)
    misfits = PosteriorMisfits(dataset, args.model)
    if not misfits.available:
        raise SystemExit(f"{args.model} has no fitted noise model, the misfit's unit: run its noise stage first")
    labels = dataset.class_labels
    posteriors = {name: p for name, p in cached_train_posteriors(dataset, args.run, args.likelihood).items() if p}
    if not posteriors:
        raise SystemExit(f"{args.run} holds no cached train posteriors for {args.likelihood}")
    right = {"fit": [], **{name: [] for name in FEATURES}}
    for held in posteriors:
        others = {n: ps for n, ps in posteriors.items() if n != held}
        learnt = {name: rules_learnt_from(fit_rules, others, labels, features, misfits)
                  for name, features in FEATURES.items()}
        truth = labels[held].material
        for index, post in posteriors[held].items():
            right["fit"].append(fit_rules.decide(post.program.samples)["material"] == truth)
            for name, rules in learnt.items():
                right[name].append(rules.decide(post.program.samples, misfits.for_rules(rules, index, post))["material"]
                                   == truth)
    print(json.dumps({"run": args.run, "likelihood": args.likelihood, "classes": len(posteriors),
                      "posteriors": len(right["fit"]),
                      "material_accuracy": {k: round(float(np.mean(v)), 3) for k, v in right.items()}}, indent=2))


if __name__ == "__main__":
    main()
