"""Should protoprograms carry the material kind as a term of their own? Decided on *train* classes.

The paper's programs hold the material as four continuous weights (k_a, k_d, k_s, alpha). Once the
concept spread widens them by how much they vary within a class (a metal's highlights move from
image to image), they hardly tell a metal from a rubber of a near colour: on dark's test split most
1-shot confusions of images whose attributes were all read right were between classes of another
material kind. The material rule (``evaluate``'s, learnt on train posteriors: weights, saturation,
Phong misfit) reads the kind far better. This asks whether a discrete ``kind`` term, the KL between
two categorical kind distributions (each image's p(metal) from the rule, a class's the mean over its
shots, both mixed with the uniform at the rule's error rate, as the shape's class term is), improves
held-out train classes' episodes.

Honest on train classes throughout: each train posterior's p(metal) comes from a rule learnt with
its own class held out (leave one class out); the classes are split in two halves, and each half's
episodes use the concept spread and the kind's error rate fitted on the other half. Loads the cached
train posteriors of an evaluation run and renders each one's Phong misfit once.

    python experiments/select_kind_term.py data/dark-lo out/eval-dark-tinted data/models/dark-tinted
        [--episodes 200] [--splits 4]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np
from scipy.special import log_softmax

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.concepts import ConceptSpread, DistanceConfig, ProtoProgram, _kl_matrix, fit_spread
from mitsuba_p3.evaluate.jobs import (MATERIAL_RULE_FEATURES, PosteriorMisfits, cached_train_posteriors,
                                      rules_learnt_from)
from mitsuba_p3.evaluate.metrics import held_out_episodes
from mitsuba_p3.evaluate.run import train_shapes
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel


def held_out_metal(dataset, posteriors, rules, misfits) -> dict[int, float]:
    """Each train posterior's p(metal) from the material rule learnt on every other train class."""
    labels, out = dataset.class_labels, {}
    for name, group in posteriors.items():
        others = {c: g for c, g in posteriors.items() if c != name}
        learnt = rules_learnt_from(rules, others, labels, MATERIAL_RULE_FEATURES, misfits)
        for index, post in group.items():
            out[index] = learnt.decide(post.program.samples, misfits.for_rules(learnt, index, post))["p_metal"]
    return out


def kind_probabilities(p_metal: float, error: float) -> np.ndarray:
    """(rubber, metal) mixed with the uniform so that a certain kind keeps 1 - error (as the concept spread
    mixes a shape's class distribution)."""
    return ConceptSpread({}, error).class_mixture(np.array([1.0 - p_metal, p_metal]))


def episodes(fold: dict, metal: dict, error: float, n_way: int, k_shot: int, count: int, seed: int,
             config: DistanceConfig, with_kind: bool) -> float:
    """Accuracy of seeded episodes among ``fold`` (class -> [(index, program)]), as
    :func:`mitsuba_p3.evaluate.metrics.held_out_accuracy` draws them, with or without the kind term."""
    correct = []
    for chosen, picks in held_out_episodes({c: len(g) for c, g in fold.items()}, n_way, k_shot, count, seed):
        support = [[fold[c][s] for s in pick[:-1]] for c, pick in zip(chosen, picks)]
        queries = [fold[c][pick[-1]] for c, pick in zip(chosen, picks)]
        classes = [ProtoProgram.merge([p for _, p in shots]) for shots in support]
        distances = sum(_kl_matrix(classes, [p for _, p in queries], config).values())   # (queries, classes)
        if with_kind:
            q = np.stack([kind_probabilities(metal[i], error) for i, _ in queries])
            c = np.stack([kind_probabilities(np.mean([metal[i] for i, _ in shots]), error) for shots in support])
            # KL(C_I || C_k), the direction of the default distance
            distances = distances + (np.sum(q * np.log(q), axis=1)[:, None] - q @ np.log(c).T)
        predicted = np.argmax(log_softmax(-distances, axis=1), axis=1)
        correct += list(predicted == np.arange(n_way))
    return float(np.mean(correct))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path, help="an evaluation run holding train posteriors")
    parser.add_argument("model", type=Path, help="the model the run used (for the Phong misfit)")
    parser.add_argument("--episodes", type=int, default=200)
    parser.add_argument("--splits", type=int, default=4, help="random halvings of the train classes")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    config = DistanceConfig()
    posteriors = {c: g for c, g in cached_train_posteriors(dataset, args.run, "p3", config.max_points).items() if g}
    misfits = PosteriorMisfits(dataset, args.model)
    rules = rules_for(FittedModel(args.model), dataset)
    metal = held_out_metal(dataset, posteriors, rules, misfits)
    labels = dataset.class_labels
    truth = {i: labels[c].material == "metal" for c, g in posteriors.items() for i in g}
    print(f"{len(metal)} train posteriors; held-out material rule right for "
          f"{np.mean([(metal[i] > 0.5) == truth[i] for i in metal]):.1%}", flush=True)
    names = sorted(posteriors)
    shapes = train_shapes(dataset)
    settings = [(5, 1), (10, 1)] + ([(5, 2), (10, 2)] if min(len(g) for g in posteriors.values()) >= 3 else [])
    cells = {False: [], True: [], "per kind": []}
    for split in range(args.splits):
        order = list(np.random.default_rng([args.seed, split]).permutation(names))
        folds = [order[:len(order) // 2], order[len(order) // 2:]]
        for f, fold in enumerate(folds):
            other = folds[1 - f]
            spread = fit_spread({c: [p.program for p in posteriors[c].values()] for c in other}, shapes)
            error = float(np.mean([1.0 - (metal[i] if truth[i] else 1.0 - metal[i])
                                   for c in other for i in posteriors[c]]))
            programs = {c: [(i, p.program.with_spread(spread)) for i, p in posteriors[c].items()] for c in fold}
            for with_kind in (False, True):
                cells[with_kind].append([episodes(programs, metal, error, n, k, args.episodes, args.seed + split,
                                                  config, with_kind) for n, k in settings])
            # a spread per material kind (fitted on the other half's classes of that kind), each program
            # taking its own kind's as the held-out rule reads it
            by_kind = {kind: fit_spread({c: [p.program for p in posteriors[c].values()] for c in other
                                         if (labels[c].material == "metal") == kind}, shapes) for kind in (False, True)}
            programs = {c: [(i, p.program.with_spread(by_kind[metal[i] > 0.5])) for i, p in posteriors[c].items()]
                        for c in fold}
            cells["per kind"].append([episodes(programs, metal, error, n, k, args.episodes, args.seed + split,
                                               config, False) for n, k in settings])
        print(f"split {split}: without {np.mean(cells[False][-2:], axis=0).round(3).tolist()}, with the kind term "
              f"{np.mean(cells[True][-2:], axis=0).round(3).tolist()}, a spread per kind "
              f"{np.mean(cells['per kind'][-2:], axis=0).round(3).tolist()} (kind error {error:.3f})", flush=True)
    names_out = [f"{n}-way {k}-shot" for n, k in settings]
    report = {{False: "without", True: "with kind"}.get(k, k): dict(zip(names_out, (100 * np.mean(v, axis=0)).round(2).tolist()))
              for k, v in cells.items()}
    print(json.dumps(report))


if __name__ == "__main__":
    main()
