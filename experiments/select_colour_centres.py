"""Which colour centres? The fit's materials against the train posteriors', leave one class out.

The colour rule (:class:`~mitsuba_p3.fit.attributes.AttributeRules`) names a posterior's colour
by the nearest *centre*, a chromaticity per train colour and material kind. Two sources:

- ``fit``: the chromaticity of each fitted material (``materials.json``), the rule of
  ``infer`` without ``--material-rule``;
- ``posteriors``: the mean chromaticity of the train posteriors' median reflectances of
  that colour and kind, so the rule is learnt on the kind of input it is applied to, as the
  material rule learnt on posteriors is; ``evaluate``'s rule since the twenty-sixth session
  (:meth:`~mitsuba_p3.fit.attributes.AttributeRules.with_colours_from_posteriors`). A colour
  and kind held by the held-out class only keeps its fit centre.

Each train class is held out in turn: the ``posteriors`` centres are made without its
posteriors and scored on them (the ``fit`` centres are fixed). Prints JSON per run: colour
accuracy per source and the misread images. Choose on train classes; the test split is for
the final figure.

    python experiments/select_colour_centres.py data/studio-lo \\
        --run out/studio-train-white=data/models/studio-white
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import cached_train_posteriors, colours_learnt_from
from mitsuba_p3.fit.attributes import median_chromaticity, rules_for
from mitsuba_p3.fit.model import FittedModel
from score_train_attributes import run_specs  # the sibling experiment's --run RUN=MODEL


def held_out_centres(rules, posteriors: dict, labels: dict, held_out: str):
    """``rules`` with the centres learnt as ``evaluate`` learns them
    (:func:`~mitsuba_p3.evaluate.jobs.colours_learnt_from`) from the train posteriors (class name ->
    {index: posterior}) of every class but ``held_out``."""
    return colours_learnt_from(rules, {name: group for name, group in posteriors.items() if name != held_out}, labels)


def compare(dataset, run: Path, model: Path, likelihood: str) -> dict:
    """Colour accuracy of both sources on one run's cached train posteriors, each class held out."""
    rules = rules_for(FittedModel(model), dataset, learnt=False)    # the fit's own materials
    labels = dataset.class_labels
    posteriors = {name: p for name, p in cached_train_posteriors(dataset, run, likelihood).items() if p}
    if not posteriors:
        raise SystemExit(f"{run} holds no cached train posteriors for {likelihood}")
    right = {"fit": 0, "posteriors": 0}
    misread = {"fit": [], "posteriors": []}
    count = 0
    for name, group in posteriors.items():
        truth = labels[name].colour
        sources = {"fit": rules, "posteriors": held_out_centres(rules, posteriors, labels, name)}
        for index, post in group.items():
            count += 1
            c = median_chromaticity(post.program.samples)
            for source, r in sources.items():
                named = r.colour_name(c)
                right[source] += named == truth
                if named != truth:
                    misread[source].append(f"{name}#{index}: {named}")
    return {"model": str(model), "posteriors": count,
            **{f"colour_{source}": round(right[source] / count, 3) for source in right}, "misread": misread}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--run", action="append", required=True, help="RUN=MODEL (repeatable)")
    parser.add_argument("--likelihood", default="p3")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    out = {str(run): compare(dataset, run, model, args.likelihood) for run, model in run_specs(parser, args.run)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
