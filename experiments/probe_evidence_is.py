"""Does an importance-sampling estimate of each run's evidence agree across runs better than SMC's own?

Two independent SMC runs of one hypothesis that find the same optimum can still estimate its log evidence
10-50 nats apart (notebook, "What the island gaps are made of"): the tempered estimate multiplies the
incremental weights of every temperature, and its error is the path's, not the posterior's. Once a run has
reached lambda = 1 its final particles show where the posterior lies, and an importance-sampling estimate from
a proposal fitted to them,

    Z_h ~= (1 / M) sum_m p(z_m | h) L(z_m) / q(z_m),    z_m ~ q,

is unbiased for any q that covers the posterior, and has a small variance when q is close to it. Each run's
proposal is fitted to its own particles only, so two runs stay independent: if they found the same optimum,
their estimates agree to the importance weights' error; if one missed it, its q covers only the worse optimum
and the gap stays (a search failure must still show).

This reads an evaluation's cached final particles, scores every run again (checked: the
cached particles' log likelihoods come back), and for each run draws ``--draws`` points from a proposal fitted
to its particles: ``t`` (one multivariate Student-t at the particles' mean and covariance, inflated) or ``kde``
(a Student-t kernel on every particle, the particles' covariance times a bandwidth); ``--fold`` fits the t in the
particles' symmetry chart and spreads it over the four quarter-turn copies (what
:mod:`mitsuba_p3.infer.importance` does); ``--iterations`` refits it to the draws' weights (population Monte
Carlo). Prints per image the leading hypothesis's SMC gap, IS gap, each run's IS effective sample size, and over
images the gaps and the shapes read from the tempered (SMC), the importance (IS) and the two estimates' mean
(MIX). Train images only unless ``--split test``.

    python experiments/probe_evidence_is.py data/dark-lo out/eval-dark-tinted --model data/models/dark-tinted \
        [--draws 256] [--proposal kde] [--images 30]
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from types import SimpleNamespace

import numpy as np
from scipy import special

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import posterior_path
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer import importance
from mitsuba_p3.infer.evidence import pooled_evidence
from mitsuba_p3.infer.posterior import PosteriorModel, default_likelihood
from mitsuba_p3.infer.smc import outside_window
from mitsuba_p3.infer.smc_config import SMCConfig
from mitsuba_p3.infer.smc_moves import kernels_for
from mitsuba_p3.infer.symmetry import chart_centres, folded, quarter_turn
from mitsuba_p3.infer.hypotheses import hypotheses_of
from mitsuba_p3.shapes import SHAPES

FREE = importance.FREE


def t_logpdf(x: np.ndarray, mean: np.ndarray, chol: np.ndarray, dof: float) -> np.ndarray:
    """log density of a multivariate Student-t (scale chol chol^T) at x (M, d)."""
    return importance._t_logpdf(x, mean, chol, dof)


def t_draws(rng, mean, chol, dof, count):
    g = rng.standard_normal((count, len(mean))) @ chol.T
    return mean + g / np.sqrt(rng.chisquare(dof, count) / dof)[:, None]


def proposal(particles: np.ndarray, kind: str, inflate: float, dof: float, rng, count: int):
    """Draws (count, d), their log density under the proposal fitted to ``particles`` (N, d), and the fitted
    t's (mean, Cholesky factor, dof) (None for ``kde``)."""
    d = particles.shape[1]
    cov = np.cov(particles.T) + 1e-6 * np.eye(d)
    if kind == "t":
        chol = np.linalg.cholesky(inflate ** 2 * cov)
        mean = particles.mean(axis=0)
        x = t_draws(rng, mean, chol, dof, count)
        return x, t_logpdf(x, mean, chol, dof), (mean, chol, dof)
    # kde: Silverman's bandwidth for d dimensions times ``inflate``
    unique = np.unique(particles, axis=0)
    h = inflate * (4 / (d + 2)) ** (1 / (d + 4)) * len(unique) ** (-1 / (d + 4))
    chol = np.linalg.cholesky(h ** 2 * cov)
    centres = unique[rng.integers(len(unique), size=count)]
    x = centres + t_draws(rng, np.zeros(d), chol, dof, count)
    logs = np.stack([t_logpdf(x, c, chol, dof) for c in unique])
    return x, special.logsumexp(logs, axis=0) - np.log(len(unique)), None


def shape_probabilities(index: np.ndarray, log_evidence: np.ndarray, space) -> np.ndarray:
    """p(shape | I) from per-run log evidence estimates: each hypothesis's runs pooled as the log of their mean."""
    pooled = pooled_evidence(SimpleNamespace(index=index, log_evidence=log_evidence), len(space.names))
    log_post = space.log_prior + pooled
    weights = np.exp(log_post - special.logsumexp(log_post))
    return np.array([weights[space.classes == c].sum() for c in range(len(SHAPES))])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("run", type=Path)
    parser.add_argument("--model", type=Path, required=True)
    parser.add_argument("--split", default="train")
    parser.add_argument("--images", type=int, default=30)
    parser.add_argument("--draws", type=int, default=256)
    parser.add_argument("--proposal", choices=("t", "kde"), default="t")
    parser.add_argument("--iterations", type=int, default=1,
                        help="population Monte Carlo: refit the t to the last draws' weights this many times - 1")
    parser.add_argument("--inflate", type=float, default=1.0)
    parser.add_argument("--dof", type=float, default=5.0)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--fold", action="store_true",
                        help="fit the proposal in the particles' symmetry chart and spread it over the four copies")
    parser.add_argument("--out", type=Path, help="a JSON of the per-image figures")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    run = json.loads((args.run / "run.json").read_text())
    config = SMCConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in run["sampler"].items()})
    fitted = FittedModel(args.model)
    likelihood = default_likelihood(fitted, "p3", run.get("sigma"), run["noise"])
    rng = np.random.default_rng(args.seed)
    shots = [s for s in dataset.split(args.split) if posterior_path(args.run, "p3", s.index).exists()]
    shots = shots[:: max(1, len(shots) // args.images)][: args.images]
    rows, begin = [], time.perf_counter()
    for shot in shots:
        with np.load(posterior_path(args.run, "p3", shot.index)) as f:
            index, z = f["particles_index"], f["particles_position"]
            cached_ll, smc = f["particles_loglikelihood"], f["particles_log_evidence"]
            window = tuple(int(v) for v in f["particles_window"]) or None
        image = dataset.image(shot)
        model = PosteriorModel(fitted, image, likelihood, "mitsuba")
        core = model.core
        observation = core.observe(image, window, outside_window(config)) if window else model.observation
        space = hypotheses_of(core.prior, config.kinds)
        kern = kernels_for(core, config)
        leader = index[np.argmax(smc)]
        mine = np.flatnonzero(index == leader)
        check, _ = kern.score(z, np.asarray(index, np.int32), observation)
        drift = float(np.max(np.abs(np.asarray(check) - cached_ll)))
        estimates, ess = [], []
        for r in range(len(index)):
            own = z[r].astype(np.float64)
            if args.fold:
                own = folded(own[None], chart_centres(own[None]))[0]
            free = own[:, FREE]
            x, log_q, fitted_t = proposal(free, args.proposal, args.inflate, args.dof, rng, args.draws)
            for it in range(args.iterations):
                if it:      # population Monte Carlo: the t refitted to the last draws' normalised weights
                    w = np.exp(log_w - special.logsumexp(log_w))
                    mean = w @ x
                    cov = (x - mean).T @ ((x - mean) * w[:, None]) + 1e-6 * np.eye(len(mean))
                    chol = np.linalg.cholesky(args.inflate ** 2 * cov)
                    x = t_draws(rng, mean, chol, args.dof, args.draws)
                    fitted_t = (mean, chol, args.dof)
                    log_q = t_logpdf(x, *fitted_t)
                full = np.repeat(z[r][:1], args.draws, axis=0).astype(np.float64)
                full[:, FREE] = x
                if args.fold and fitted_t is not None:       # a uniform copy of the chart's draw: q is the four copies' mixture
                    full = quarter_turn(full, rng.integers(4, size=args.draws))[0]
                    fitted = importance.Proposal(fitted_t[0][None], fitted_t[1][None], fitted_t[2], full[:1])
                    log_q = importance.log_density(fitted, full[None])[0]
                full = full.astype(np.float32)
                ll, lp = kern.score(full.reshape(1, args.draws, 15), np.asarray([index[r]], np.int32), observation)
                log_w = np.asarray(ll, np.float64)[0] + np.asarray(lp, np.float64)[0] - log_q
                log_w = np.where(np.isfinite(log_w), log_w, -np.inf)
            estimates.append(float(special.logsumexp(log_w) - np.log(args.draws)))
            w = np.exp(log_w - log_w.max())
            ess.append(float(w.sum() ** 2 / np.sum(w * w)))
        estimates = np.array(estimates)
        truth = SHAPES.index(shot.cls.name.split("-")[-1])
        mixed = np.logaddexp(smc, estimates) - np.log(2)     # the two unbiased estimates' mean
        p_smc, p_is, p_mix = (shape_probabilities(index, e, space) for e in (smc, estimates, mixed))
        row = {"index": shot.index, "class": shot.cls.name, "smc": smc[mine].tolist(), "is": estimates[mine].tolist(),
               "ess": [ess[r] for r in mine], "smc_gap": float(np.ptp(smc[mine])),
               "is_gap": float(np.ptp(estimates[mine])) if len(mine) > 1 else 0.0,
               "best_spread": float(np.ptp(cached_ll[mine].max(axis=1))), "drift": drift,
               "p_true_smc": float(p_smc[truth]), "p_true_is": float(p_is[truth]),
               "right_smc": bool(np.argmax(p_smc) == truth), "right_is": bool(np.argmax(p_is) == truth),
               "p_true_mix": float(p_mix[truth]), "right_mix": bool(np.argmax(p_mix) == truth),
               "mix_gap": float(np.ptp(mixed[mine])) if len(mine) > 1 else 0.0,
               "index_all": index.tolist(), "smc_all": smc.tolist(), "is_all": estimates.tolist(), "ess_all": ess}
        rows.append(row)
        print(f"{shot.index:5d} {shot.cls.name:<28} SMC {' '.join(f'{v:8.1f}' for v in row['smc'])} gap "
              f"{row['smc_gap']:5.1f} | IS {' '.join(f'{v:8.1f}' for v in row['is'])} gap {row['is_gap']:5.1f} "
              f"| ESS {' '.join(f'{v:5.1f}' for v in row['ess'])} | best spread {row['best_spread']:5.1f} drift {drift:.2g}",
              flush=True)
    smc_gaps = np.array([r["smc_gap"] for r in rows])
    is_gaps = np.array([r["is_gap"] for r in rows])
    mix_gaps = np.array([r["mix_gap"] for r in rows])
    same = np.array([r["best_spread"] < 3 for r in rows])
    print(f"\n{len(rows)} {args.split} posteriors, {args.proposal} proposal, {args.draws} draws per run, "
          f"{time.perf_counter() - begin:.0f} s")
    for name, g in (("SMC", smc_gaps), ("IS", is_gaps), ("MIX", mix_gaps)):
        print(f"  {name:>3} gap median {np.median(g):5.2f}  p90 {np.percentile(g, 90):6.2f}  over 10 nats "
              f"{np.mean(g > 10):5.1%}  (runs at the same optimum: median {np.median(g[same]) if same.any() else np.nan:5.2f})")
    for name in ("smc", "is", "mix"):
        print(f"  {name.upper():>3} shapes right {sum(r['right_' + name] for r in rows)} of {len(rows)}, mean log p(true shape) "
              f"{np.mean([np.log(max(r['p_true_' + name], 1e-300)) for r in rows]):.3f}")
    print(f"  IS minus SMC per run, median {np.median([i - s for r in rows for i, s in zip(r['is'], r['smc'])]):+.2f} nats; "
          f"IS ESS median {np.median([e for r in rows for e in r['ess']]):.1f} of {args.draws}")
    if args.out:
        args.out.write_text(json.dumps({"args": {k: str(v) for k, v in vars(args).items()}, "rows": rows}, indent=1))


if __name__ == "__main__":
    main()
