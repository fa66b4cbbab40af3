"""Simulation-based calibration of the default sampler (tempered SMC) on its own model.

Draws ``--images`` scenes from a fitted model's prior, renders each with the Phong
model plus the likelihood's noise, samples its posterior, and prints JSON: per checked
coordinate (position, log half-extents, colour) the KS and chi-square p-values of its ranks'
uniformity and whether its ECDF difference stays inside the simultaneous 95% band, and the
shape posterior's calibration (:mod:`mitsuba_p3.evaluate.sbc` explains the method). Writes
``OUT/sbc.json``, ``OUT/sbc.png`` (ECDF differences with their bands, rank histograms),
``OUT/calibration.png`` (the shape's reliability diagram) and ``OUT/cache.npz``, which a killed
run resumes from.

    python scripts/sbc.py --model data/models/fsclvr [--images 200] [--draws 99] [--out out/sbc]
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

from mitsuba_p3.evaluate.sbc import CHECKED, ecdf_bands, ecdf_difference, run_sbc
from mitsuba_p3.files import atomic_json
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.likelihood import LikelihoodConfig
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.evidence import shape_weights
from mitsuba_p3.infer.smc import SMCConfig, sample_smc


def smc_sampler(core, config: SMCConfig):
    """The SBC's view of the SMC: observation, seed -> (positions, class probabilities)."""
    from dataclasses import replace

    def sample(observation, seed):
        run = sample_smc(core, observation, replace(config, seed=seed))
        probabilities = np.array(list(shape_weights(run.statistics).values()))
        return run.positions.reshape(-1, run.positions.shape[-1]), probabilities

    return sample


def plot_report(summary: dict, result, path: Path) -> None:
    """The SBC figure: per coordinate the ECDF difference with its simultaneous 95% band (top two
    rows) and the rank histogram with a uniform histogram's 99% band (bottom two), and the shape
    posterior's reliability diagram (a separate ``calibration.png`` beside ``path``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import binom

    n, bins = summary["images"], summary["bins"]
    z, lower, upper = ecdf_bands(n)
    difference = ecdf_difference(result.ranks, result.draws, z)
    fig, axes = plt.subplots(4, 4, figsize=(13, 9))
    for j, (ax, name) in enumerate(zip(axes[:2].ravel(), CHECKED)):
        ax.fill_between(z, lower, upper, color="0.85", lw=0)
        inside = summary["ecdf_inside_95_band"][name]
        ax.plot(z, difference[:, j], color="tab:blue" if inside else "tab:red", lw=1.2)
        ax.axhline(0, color="0.5", lw=0.6)
        ax.set_title(f"{name}  KS p={summary['rank_uniformity_ks_p'][name]:.2g}", fontsize=9)
        ax.tick_params(labelsize=7)
    low, high = binom.ppf([0.005, 0.995], n, 1 / bins)
    for ax, name in zip(axes[2:].ravel(), CHECKED):
        ax.axhspan(low, high, color="0.85")
        ax.bar(np.arange(bins), summary["rank_counts"][name], color="tab:blue")
        ax.set_title(f"{name}  chi2 p={summary['rank_uniformity_p'][name]:.2g}", fontsize=9)
        ax.set_xticks([])
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("ECDF - uniform")
    axes[2][0].set_ylabel("rank count")
    fig.suptitle(f"SBC: {n} simulations, {summary['draws']} draws each. Top: ECDF difference, grey the "
                 "simultaneous 95% band (red: leaves it). Bottom: rank histograms, grey a uniform's 99% band",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    bins_ = [b for b in summary["class"]["reliability"] if b[2] > 0]
    fig, ax = plt.subplots(figsize=(3.6, 3.4))
    ax.plot([0, 1], [0, 1], ls="--", color="0.6", lw=1)
    ax.plot([b[0] for b in bins_], [b[1] for b in bins_], "o-", color="tab:blue")
    for b in bins_:
        ax.annotate(str(b[2]), (b[0], b[1]), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xlabel("confidence of the modal shape")
    ax.set_ylabel("share correct")
    ax.set_title(f"shape calibration: ECE {summary['class']['ece']:.3f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path.with_name("calibration.png"), dpi=110)
    plt.close(fig)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--images", type=int, default=200)
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
    plot_report(summary, result, args.out / "sbc.png")
    shown = {k: v for k, v in summary.items() if k != "rank_counts"}
    shown["class"] = {k: v for k, v in summary["class"].items() if k != "reliability"}
    print(json.dumps(shown, indent=2))


if __name__ == "__main__":
    main()
