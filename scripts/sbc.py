"""Simulation-based calibration of the default sampler (tempered SMC) on its own model.

Draws ``--images`` scenes from a fitted model's prior, renders each with the Phong
model plus the likelihood's noise, samples its posterior, and prints JSON: the
chi-square p-value of each checked coordinate's rank histogram (position, log
half-extents, colour) and the shape posterior's calibration
(:mod:`mitsuba_p3.evaluate.sbc` explains the method). Writes ``OUT/sbc.json``,
``OUT/ranks.png`` (one rank histogram per coordinate, the band of a uniform
histogram's 99% range shaded) and ``OUT/cache.npz``, which a killed run resumes from.

    python scripts/sbc.py --model data/models/fsclvr [--images 100] [--draws 99] [--out out/sbc]
        [--noise fitted|sandwich]

``--noise`` picks the power of the model's Gaussian noise: 1 / correlation area (fitted) or the
sandwich power along the pose (sandwich); either way the images are simulated at the effective
sigma / sqrt(power) that inference uses.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.evaluate.sbc import CHECKED, run_sbc
from mitsuba_p3.files import atomic_json
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.likelihood import LikelihoodConfig
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.smc import SMCConfig, sample_smc, shape_weights


def smc_sampler(core, config: SMCConfig):
    """The SBC's view of the SMC: observation, seed -> (positions, class probabilities)."""
    from dataclasses import replace

    def sample(observation, seed):
        run = sample_smc(core, observation, replace(config, seed=seed))
        probabilities = np.array(list(shape_weights(run.statistics).values()))
        return run.positions.reshape(-1, run.positions.shape[-1]), probabilities

    return sample


def plot_ranks(summary: dict, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import binom

    n, bins = summary["images"], summary["bins"]
    low, high = binom.ppf([0.005, 0.995], n, 1 / bins)
    fig, axes = plt.subplots(2, 4, figsize=(12, 5), sharey=True)
    for ax, name in zip(axes.ravel(), CHECKED):
        ax.axhspan(low, high, color="0.85")
        ax.bar(np.arange(bins), summary["rank_counts"][name], color="tab:blue")
        ax.set_title(f"{name}  p={summary['rank_uniformity_p'][name]:.2f}", fontsize=9)
        ax.set_xticks([])
    fig.suptitle(f"SBC rank histograms ({n} simulations, {summary['draws']} draws each; grey: 99% band of uniform)")
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--images", type=int, default=100)
    parser.add_argument("--draws", type=int, default=99)
    parser.add_argument("--particles", type=int, default=SMCConfig.particles)
    parser.add_argument("--resolution", default="120x160")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--out", type=Path, default=Path("out/sbc"))
    parser.add_argument("--noise", default="fitted", choices=("fitted", "sandwich"))
    args = parser.parse_args()

    fitted = FittedModel(args.model)
    noise = fitted.noise
    height, width = (int(v) for v in args.resolution.split("x"))
    # the tempered likelihood inference uses, written as the untempered one it equals: sigma / sqrt(beta)
    power = noise.power if args.noise == "fitted" else noise.pose_power
    if power is None:
        raise SystemExit(f"{args.model} has no sandwich power: refit its noise stage (mitsuba-p3 fit ... --stages noise)")
    likelihood = LikelihoodConfig("p3", sigma=noise.gaussian_sigma / np.sqrt(power), shadows=noise.shadows)
    core = PosteriorCore(fitted, likelihood, "mitsuba", height, width)
    args.out.mkdir(parents=True, exist_ok=True)
    result = run_sbc(core, smc_sampler(core, SMCConfig(particles=args.particles)), args.images, args.draws,
                     args.seed, cache=args.out / "cache.npz",
                     progress=lambda i, n: print(f"sbc {i}/{n}", flush=True))
    summary = {"model": args.model, "noise": args.noise, "likelihood_sigma": likelihood.sigma, **result.summary()}
    atomic_json(args.out / "sbc.json", summary)
    plot_ranks(summary, args.out / "ranks.png")
    print(json.dumps({k: v for k, v in summary.items() if k != "rank_counts"}, indent=2))


if __name__ == "__main__":
    main()
