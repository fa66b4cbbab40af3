"""Can the attribute rules be learnt without sampling train posteriors? The material at the true pose.

``evaluate`` learns its material rule and colour centres from train posteriors (the full SMC over
pose, shape and material), because the fit's own materials are a different kind of input than a
posterior's medians (docs/notebook.md, "Keep the start the noise model explains best"). ``infer``
alone has no train posteriors. This probe asks whether a far cheaper input will do: the material's
conditional posterior *at the labelled pose and shape* of train images
(:func:`mitsuba_p3.infer.truth_rules.truth_draws`: the sampler's own material moves under the default
likelihood and scoring window, from the fit's material of the image's class).

For the first ``--images`` train images of every class it draws that conditional (and measures the
image's Phong misfit at its labelled pose), and prints JSON per run: how far each draw set's median
chromaticity lies from its class's cached train posteriors'; and the colour and material accuracy on
those cached train posteriors of five rules, each class held out in turn: the fit's own (``fit``);
learnt from the other classes' train posteriors on the Phong weights and the reflectance's saturation
(``posteriors``) and with each posterior's Phong misfit too (``posteriors+misfit``, evaluate's rule);
learnt from the other classes' truth-pose draws without the misfit (``truth-without-misfit``) and with
the misfit at the labelled pose (``truth``). The learnt rules weigh their examples as they come, and the two
with the misfit are also learnt with the kinds weighed equally (``posteriors+misfit balanced`` and ``truth
balanced``, what ``evaluate`` and ``fit`` now learn: :data:`mitsuba_p3.fit.attributes.KIND_WEIGHTS`); the
fit's own rule (``fit``) follows that setting. Every material share is printed also as the mean of the two
kinds' shares (``material_balanced_...``), which a rule's prior on the kinds cannot buy.

    python experiments/probe_material_at_truth.py data/fsclvr-lo --run out/train-white-s1=data/models/fsclvr-white-s1

``--test`` scores the same five rules, each learnt from every train class (the posteriors' from the
run's cached train posteriors), on the run's cached *test* posteriors instead (an evaluation's run
folder): a final figure, nothing is chosen on it.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import (CachedPosterior, PosteriorMisfits, cached_train_posteriors, colours_learnt_from,
                                      posterior_path, rules_learnt_from)
from mitsuba_p3.fit import attributes
from mitsuba_p3.fit.attributes import median_chromaticity, rules_for
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.truth_rules import BURN, FEATURES, IMAGES, MOVES, rules_from_draws, truth_draws
from score_train_attributes import run_specs  # the sibling experiment's --run RUN=MODEL

WITHOUT_MISFIT = "weights+saturation"


def learnt_rules(rules, posteriors: dict, draws: list, labels: dict, misfits) -> dict:
    """The rules compared (module docstring), the learnt ones from these train ``posteriors`` (class
    name -> {index: posterior}) and truth-pose ``draws`` ((class name, draws) pairs); the two with the misfit
    also with the kinds weighed equally (``... balanced``, :data:`~mitsuba_p3.fit.attributes.KIND_WEIGHTS`)."""
    def from_posteriors(features):
        return colours_learnt_from(rules_learnt_from(rules, posteriors, labels, features, misfits), posteriors, labels)

    def weighed(weights, make):
        previous, attributes.KIND_WEIGHTS = attributes.KIND_WEIGHTS, weights
        try:
            return make()
        finally:
            attributes.KIND_WEIGHTS = previous

    truth = lambda features=FEATURES: rules_from_draws(rules, draws, labels, features)  # noqa: E731
    return {"fit": rules,
            "posteriors": weighed(None, lambda: from_posteriors(WITHOUT_MISFIT)),
            "posteriors+misfit": weighed(None, lambda: from_posteriors(FEATURES)),
            "truth-without-misfit": weighed(None, lambda: truth(WITHOUT_MISFIT)),
            "truth": weighed(None, truth),
            "posteriors+misfit balanced": weighed("balanced", lambda: from_posteriors(FEATURES)),
            "truth balanced": weighed("balanced", truth)}


def tally(right: dict, sources: dict, index: int, post, truth, misfits) -> None:
    """Add one posterior's colour and material decisions under every rule of ``sources`` to ``right``
    (the material's also by the image's true kind, for the accuracy with the kinds weighed equally)."""
    for source, r in sources.items():
        decided = r.decide(post.program.samples, misfits.for_rules(r, index, post))
        right["colour"][source] = right["colour"].get(source, 0) + (decided["colour"] == truth.colour)
        right["material"][source] = right["material"].get(source, 0) + (decided["material"] == truth.material)
        by_kind = right.setdefault(f"material_{truth.material}", {})
        by_kind[source] = by_kind.get(source, 0) + (decided["material"] == truth.material)
    right.setdefault("count", {}).setdefault(truth.material, 0)
    right["count"][truth.material] += 1


def shares(right: dict, count: int) -> dict:
    """Each rule's share right of colour and material; its material share right with the kinds weighed
    equally (the mean of the two kinds' shares)."""
    out = {f"{attribute}_{source}": round(n / max(count, 1), 3) for attribute, by in right.items()
           if attribute in ("colour", "material") for source, n in by.items()}
    kinds = right.get("count", {})
    if len(kinds) == 2:
        out.update({f"material_balanced_{source}": round(float(np.mean(
            [right[f"material_{kind}"][source] / n for kind, n in kinds.items()])), 3) for source in right["material"]})
    return out


def probe(dataset, run, model, images: int, moves: int, burn: int, likelihood: str) -> dict:
    """The five rules on the run's cached train posteriors, each class held out in turn."""
    fitted = FittedModel(model)
    rules = rules_for(fitted, dataset, learnt=False)
    labels = dataset.class_labels
    posteriors = {name: group for name, group in cached_train_posteriors(dataset, run, likelihood).items() if group}
    draws = truth_draws(fitted, dataset, images, moves, burn,
                        lambda done, total: print(f"\r{run}: {done}/{total} truth-pose images", end="", flush=True))
    print(flush=True)
    centre = {name: np.mean([median_chromaticity(p.program.samples) for p in group.values()], axis=0)
              for name, group in posteriors.items()}
    gaps = [float(np.linalg.norm(median_chromaticity(d) - centre[name])) for name, d in draws if name in centre]
    misfits = PosteriorMisfits(dataset, Path(model))
    right, count = {"colour": {}, "material": {}}, 0
    for held in posteriors:
        sources = learnt_rules(rules, {n: g for n, g in posteriors.items() if n != held},
                               [(n, d) for n, d in draws if n != held], labels, misfits)
        for index, post in posteriors[held].items():
            count += 1
            tally(right, sources, index, post, labels[held], misfits)
    return {"model": str(model), "posteriors": count, "truth_pose_images": len(draws),
            "chromaticity_gap_to_class_posteriors": {"median": round(float(np.median(gaps)), 4),
                                                     "p90": round(float(np.percentile(gaps, 90)), 4)},
            **shares(right, count)}


def score_test(dataset, run, model, images: int, moves: int, burn: int, likelihood: str) -> dict:
    """The five rules, each learnt on all train classes, scored on the run's cached test posteriors."""
    fitted = FittedModel(model)
    labels = dataset.class_labels
    train = {name: group for name, group in cached_train_posteriors(dataset, run, likelihood).items() if group}
    misfits = PosteriorMisfits(dataset, Path(model))
    sources = learnt_rules(rules_for(fitted, dataset, learnt=False), train,
                           truth_draws(fitted, dataset, images, moves, burn), labels, misfits)
    right, count = {"colour": {}, "material": {}}, 0
    for shot in dataset.split("test"):
        path = posterior_path(run, likelihood, shot.index)
        if path.exists():
            count += 1
            tally(right, sources, shot.index, CachedPosterior.load(path, 500), labels[shot.class_name], misfits)
    return {"model": str(model), "test_posteriors": count, **shares(right, count)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--run", action="append", required=True, help="RUN=MODEL (repeatable)")
    parser.add_argument("--images", type=int, default=IMAGES, help="train images per class at the true pose")
    parser.add_argument("--moves", type=int, default=MOVES, help="material moves per image")
    parser.add_argument("--burn", type=int, default=BURN, help="moves dropped at the start")
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--test", action="store_true", help="score on the run's cached test posteriors")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    score = score_test if args.test else probe
    out = {str(run): score(dataset, run, model, args.images, args.moves, args.burn, args.likelihood)
           for run, model in run_specs(parser, args.run)}
    print(json.dumps(out, indent=2))


if __name__ == "__main__":
    main()
