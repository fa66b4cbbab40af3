"""Do more rounds of runs settle a close call? Each seed's shape posterior after 1, 2, ... R rounds, read
from posteriors sampled with up to R rounds.

A posterior of ``SMCConfig(rounds=R)`` keeps every run's log evidence in the order the runs were made
(``particles_index``, ``particles_log_evidence``). Its first r rounds are the runs a sampler with
``rounds=r`` would have made under the same seed (the rounds split the same key in the same order), so
replaying the rounds' rule (:func:`mitsuba_p3.infer.evidence.decision`) on the cached runs gives each
seed's posterior over shapes after r rounds, for every r, from one sampling. Per r it prints, over the
images: the share whose modal shape every seed agrees on, the median spread across seeds of the log odds
of the two leading shapes, the mean p(true shape) and the runs spent per posterior; and the same for a rule that
stops a seed at the first round whose leader holds against k = 2 standard errors of the pooled evidence
(``rounds_se``, :func:`standard_error_decided`), which, unlike the extremes the sampler's rule reads, can decide as
runs accumulate.

    python scripts/bench_infer.py --dataset data/fsclvr-lo --model data/models/fsclvr-white-s1 --split train \\
        --shots 24,25 --configs smc-fields-rounds4 --seeds 2 --out out/rounds4
    python experiments/probe_rounds.py data/fsclvr-lo data/models/fsclvr-white-s1 out/rounds4/smc-fields-rounds4-seed*
        [--check out/eval-fsclvr-s1]

``--check RUN`` compares each image's replay after the run's own number of rounds with the posterior that RUN
(an evaluation or bench folder of the same seed and fewer rounds) cached for it: their log evidences must
match, which checks the replay.
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


def pooled_of(runs: list[np.ndarray]) -> np.ndarray:
    """log Z per hypothesis: the log of the mean of its runs' estimates."""
    return np.array([np.logaddexp.reduce(m) - np.log(len(m)) for m in runs])


def standard_error_decided(log_prior: np.ndarray, runs: list[np.ndarray], threshold: float, k: float = 2.0) -> bool:
    """A rule that can decide as runs accumulate (the extremes of :func:`decision` only widen): the leader keeps
    weight ``threshold`` with its pooled evidence lowered, and every other's raised, by k standard errors of the
    log of the runs' mean, sqrt((n sum w^2 - 1) / (n - 1)) with w each run's share of the summed evidence (the
    relative standard error of a mean; infinite for one run)."""
    pooled = pooled_of(runs)
    error = np.array([np.sqrt(max(len(m) * np.sum(np.exp(2 * (m - np.logaddexp.reduce(m)))) - 1, 0) / (len(m) - 1))
                      if len(m) > 1 else np.inf for m in runs])
    leader = int(np.argmax(log_prior + pooled))
    worst = log_prior + pooled + np.where(np.arange(len(runs)) == leader, -k, k) * error
    return bool(np.exp(worst[leader] - np.logaddexp.reduce(worst)) >= threshold) if np.all(np.isfinite(worst)) else False


def replay(index: np.ndarray, log_evidence: np.ndarray, log_prior: np.ndarray, islands: int, threshold: float):
    """Per round r = 1, 2, ...: (pooled log evidence per hypothesis, runs so far, whether the standard-error rule
    would stop here), replaying the rounds' rule on a posterior's runs in the order they were made."""
    count, used, contenders, out = len(log_prior), 0, np.arange(len(log_prior)), []
    while used < len(index):
        size = len(contenders) * islands
        if not np.array_equal(index[used:used + size], np.tile(contenders, islands)):
            raise ValueError(f"the runs after the first {used} are not a round of {contenders.tolist()}")
        used += size
        mine = [log_evidence[:used][index[:used] == h] for h in range(count)]
        pooled = pooled_of(mine)
        low, high = np.array([m.min() for m in mine]), np.array([m.max() for m in mine])
        out.append((pooled, used, standard_error_decided(log_prior, mine, threshold)))
        decided, contenders = decision(log_prior, pooled, low, high, threshold)
        if decided or len(contenders) < 2:
            break
    return out


def shape_probabilities(pooled: np.ndarray, log_prior: np.ndarray) -> np.ndarray:
    weights = log_prior + pooled
    return np.exp(weights - np.logaddexp.reduce(weights))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("model")
    parser.add_argument("runs", nargs="+", type=Path, help="run folders of one setting, one per seed")
    parser.add_argument("--check", type=Path, default=None)
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    log_prior = np.log(np.asarray(FittedModel(args.model).prior.config.class_probabilities, np.float64))
    settings = [json.loads((run / "run.json").read_text())["sampler"] for run in args.runs]
    islands, threshold = settings[0]["islands"], settings[0]["decided"]
    images = sorted(set.intersection(*({int(p.stem) for p in (run / "posteriors" / "p3").glob("*.npz")}
                                       for run in args.runs)))
    rounds = max(s["rounds"] for s in settings)
    table = {r: {"agree": [], "spread": [], "p_true": [], "runs": []} for r in [*range(1, rounds + 1), "se"]}
    for image in images:
        shape = dataset.shots[image].cls.shape
        true = SHAPES.index(shape) if shape in SHAPES else None     # ood's shapes are none of them
        per_seed = []
        for run in args.runs:
            cached = np.load(posterior_path(run, "p3", image))
            steps = replay(cached["particles_index"], cached["particles_log_evidence"], log_prior, islands, threshold)
            per_seed.append(steps)
            if args.check is not None and run == args.runs[0] and posterior_path(args.check, "p3", image).exists():
                other = np.load(posterior_path(args.check, "p3", image))
                made = len(other["particles_index"])
                kept = next((pooled for pooled, used, _ in steps if used == made), None)
                same = kept is not None and np.allclose(kept, other["log_evidence"])
                print(f"check {image}: {'same' if same else 'DIFFERENT'} ({made} runs cached there)")
        line = [f"{image:5d} {dataset.shots[image].class_name:32s}"]
        for r in [*range(1, rounds + 1), "se"]:
            # "se": each seed stops at the first round the standard-error rule decides (or its last)
            at = [next((x for x in steps if x[2]), steps[-1]) if r == "se" else steps[min(r, len(steps)) - 1]
                  for steps in per_seed]
            probs = np.array([shape_probabilities(pooled, log_prior) for pooled, _, _ in at])
            modal = probs.argmax(axis=1)
            top = np.argsort(probs.mean(axis=0))[-2:]
            odds = np.log(probs[:, top[1]] + 1e-12) - np.log(probs[:, top[0]] + 1e-12)
            table[r]["agree"].append(len(set(modal)) == 1)
            table[r]["spread"].append(float(np.ptp(odds)))
            table[r]["p_true"].append(float(probs[:, true].mean()) if true is not None else np.nan)
            table[r]["runs"].append(float(np.mean([used for _, used, _ in at])))
            shown, label = (probs[:, true], "p(true)") if true is not None else (probs[:, top[1]], SHAPES[top[1]])
            line.append(f"r{r}: {label} " + "/".join(f"{p:.2f}" for p in shown))
        print("  ".join(line), flush=True)
    summary = {f"rounds_{r}": {"modal_shape_same_across_seeds": float(np.mean(v["agree"])),
                               "log_odds_spread_median": float(np.median(v["spread"])),
                               "p_true_shape_mean": (None if np.all(np.isnan(v["p_true"]))       # ood: no true shape
                                                     else float(np.nanmean(v["p_true"]))),
                               "runs_per_posterior": float(np.mean(v["runs"]))} for r, v in table.items()}
    print(json.dumps({"images": images, "seeds": len(args.runs), **summary}, indent=1))


if __name__ == "__main__":
    main()
