"""Would fewer runs per round decide as well? One run per hypothesis and round, replayed from the runs an
evaluation's posteriors cached.

The default SMC runs every hypothesis twice in its first round (two islands) and the contenders twice more
in a second round when the first leaves the answer open. Each run is an independent SMC of its hypothesis
under the same settings, so a hypothesis's cached runs are a stream of exchangeable draws of its evidence
estimate; a sampler that spends fewer of them per round can be replayed from the stream without sampling:

- ``one``: one run per hypothesis and round; after each round the rounds' rule
  (:func:`mitsuba_p3.infer.evidence.decision`) decides or keeps the contenders, up to ``--most`` runs of a
  hypothesis (the default's own most, 4);
- ``leader-twice``: the same, but the leader always gets a second run before the answer is taken, so every
  posterior keeps an island gap (its convergence diagnostic), which ``one`` loses on a decided image.

Per scheme it prints, over an evaluation's posteriors of one split (choose on ``train``), the shapes read right,
the mean p(true shape), the mean log p(true shape) and the runs per posterior, beside the default's own. A
scheme that needs more runs of a hypothesis than the cache holds is counted (``short``): the replay then
goes on without that run.

    python experiments/probe_run_streams.py data/fsclvr-lo data/models/fsclvr-white-s1 out/eval-fsclvr-s1 [--split train]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate import posterior_path
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.evidence import decision
from mitsuba_p3.shapes import SHAPES
from probe_rounds import pooled_of, shape_probabilities   # (a neighbour in experiments/)

SCHEMES = ("one", "leader-twice")


def replay_streams(streams: list[np.ndarray], log_prior: np.ndarray, threshold: float, scheme: str,
                   most: int = 4) -> tuple[np.ndarray, int, bool]:
    """(pooled log evidence per hypothesis, runs spent, whether a stream ran short) of ``scheme`` over each
    hypothesis's stream of cached run estimates, taken in order, with at most ``most`` runs of a hypothesis
    (the default's own most: two rounds of two islands). Short: the scheme asked a hypothesis for a run its
    stream does not hold (the default had stopped sooner); the replay then goes on without it."""
    if scheme not in SCHEMES:
        raise ValueError(f"unknown scheme {scheme!r}; choose from {', '.join(SCHEMES)}")
    used, asked, short = np.zeros(len(streams), int), np.arange(len(streams)), False
    while len(asked):
        used[asked] += 1
        mine = [s[:n] for s, n in zip(streams, used)]
        pooled = pooled_of(mine)
        decided, contenders = decision(log_prior, pooled, np.array([m.min() for m in mine]),
                                       np.array([m.max() for m in mine]), threshold)
        leader = int(np.argmax(log_prior + pooled))
        if scheme == "leader-twice" and used[leader] < 2:
            asked = np.array([leader]) if decided else np.union1d(contenders, [leader])
        elif decided or len(contenders) < 2:
            break
        else:
            asked = contenders
        asked = np.array([h for h in asked if used[h] < most], int)
        held = np.array([used[h] < len(streams[h]) for h in asked], bool)
        short = short or not held.all()
        asked = asked[held]
    return pooled, int(used.sum()), short


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("model")
    parser.add_argument("run", type=Path, help="an evaluation (or bench) folder of SMC posteriors")
    parser.add_argument("--split", choices=("train", "test"), default="train")
    parser.add_argument("--most", type=int, default=4, help="runs of one hypothesis at the most (default: the default's 4)")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    log_prior = np.log(np.asarray(FittedModel(args.model).prior.config.class_probabilities, np.float64))
    threshold = json.loads((args.run / "run.json").read_text())["sampler"]["decided"]
    rows = {name: {"p_true": [], "right": [], "runs": [], "short": 0} for name in ("default", *SCHEMES)}
    for shot in dataset.split(args.split):
        path = posterior_path(args.run, "p3", shot.index)
        if not path.exists() or shot.cls.shape not in SHAPES:
            continue
        cached = np.load(path)
        index, evidence = cached["particles_index"], cached["particles_log_evidence"]
        true = SHAPES.index(shot.cls.shape)
        streams = [evidence[index == h] for h in range(len(log_prior))]
        for name in rows:
            pooled, runs, short = ((pooled_of(streams), len(index), False) if name == "default" else
                                   replay_streams(streams, log_prior, threshold, name, args.most))
            probabilities = shape_probabilities(pooled, log_prior)
            rows[name]["p_true"].append(probabilities[true])
            rows[name]["right"].append(int(np.argmax(probabilities)) == true)
            rows[name]["runs"].append(runs)
            rows[name]["short"] += short
    summary = {name: {"posteriors": len(v["p_true"]),
                      "shape_right": int(np.sum(v["right"])),
                      "p_true_shape_mean": round(float(np.mean(v["p_true"])), 4),
                      "log_p_true_shape_mean": round(float(np.mean(np.log(np.maximum(v["p_true"], 1e-4)))), 4),
                      "runs_per_posterior": round(float(np.mean(v["runs"])), 2), "short": v["short"]}
               for name, v in rows.items()}
    print(json.dumps({"run": str(args.run), "split": args.split, **summary}, indent=1))


if __name__ == "__main__":
    main()
