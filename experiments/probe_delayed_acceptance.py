"""Would a delayed-acceptance walk save renders? The coarse likelihood as a screen, measured on train images.

A posterior's renders are mostly its random walk's, and the walk is tuned to 25% acceptance, so
three in four full-window renders score a proposal that is then rejected. Delayed acceptance
(Christen and Fox 2005) screens each proposal first with a cheap target -- here the coarse
likelihood (:mod:`mitsuba_p3.infer.coarse`, a quarter of the pixels) -- and renders the full window
only for proposals the screen passes:

    stage 1: pass with  a1 = min(1, [p(z') L_c(z')^lambda q(z | z')] / [p(z) L_c(z)^lambda q(z' | z)])
    stage 2: accept with a2 = min(1, [L(z') / L(z)]^lambda [L_c(z) / L_c(z')]^lambda)

which leaves the same target invariant as the plain walk (the second stage corrects the first's
approximation exactly). Its cost per proposal is a coarse render (a quarter) plus a full one with
probability a1; it accepts with probability a1 a2 <= the plain walk's. Whether it pays depends on
how well the coarse likelihood ranks proposals near the posterior, which this probe measures.

For each train image it runs the default SMC (one round), takes the leading hypothesis's final
particles, proposes the walk's Gaussian steps (the particles' covariance over position, yaw and
size, times 2.38^2 / d and a scale halved until the plain walk accepts at least 20%),
scores every proposal under both likelihoods, and prints per image and lambda: the plain walk's
acceptance; the screen's pass rate; delayed acceptance's acceptance; and its accepted moves per
full-window render equivalent against the plain walk's (> 1: it would save renders). At lambda < 1
the particles are still lambda = 1's, narrower than that temperature's posterior, so those rows
only hint at the walks earlier in a run.

    python experiments/probe_delayed_acceptance.py --dataset data/fsclvr-lo --model data/models/fsclvr-fields3 --images 4
"""
from __future__ import annotations

import argparse

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.coarse import coarse_view
from mitsuba_p3.infer.hypotheses import hypotheses_of, hypothesis_log_prior
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.smc import SMCConfig, outside_window, sample_smc
from mitsuba_p3.infer.smc_moves import WALK_MASK


def rates(full: np.ndarray, coarse: np.ndarray, prior: np.ndarray, lam: float, coarse_cost: float) -> dict:
    """Plain and delayed acceptance from (proposal - current) log likelihood differences."""
    plain = np.minimum(1.0, np.exp(np.minimum(prior + lam * full, 0.0)))
    screen = np.minimum(1.0, np.exp(np.minimum(prior + lam * coarse, 0.0)))
    second = np.minimum(1.0, np.exp(np.minimum(lam * (full - coarse), 0.0)))
    delayed = screen * second
    return {"plain": plain.mean(), "screen": screen.mean(), "delayed": delayed.mean(),
            "gain": (delayed.mean() / (coarse_cost + screen.mean())) / plain.mean()}


def main() -> None:
    import jax
    import jax.numpy as jnp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr-lo")
    parser.add_argument("--model", default="data/models/fsclvr-fields3")
    parser.add_argument("--images", type=int, default=4, help="evenly spaced train images")
    parser.add_argument("--proposals", type=int, default=4, help="walk proposals per particle")
    parser.add_argument("--lambdas", default="0.1,0.3,1.0")
    args = parser.parse_args()

    fitted = FittedModel(args.model)
    dataset = load_dataset(args.dataset)
    core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=DEFAULT_NOISE), "mitsuba", *dataset.resolution)
    shots = dataset.split("train")
    chosen = [shots[i] for i in np.linspace(0, len(shots) - 1, args.images).astype(int)]
    config = SMCConfig(rounds=1)
    mask = jnp.asarray(WALK_MASK)
    lambdas = [float(v) for v in args.lambdas.split(",")]
    log_prior = hypothesis_log_prior(core.prior, hypotheses_of(core.prior, False))
    # compiled once: the observation and the row are arguments, not constants of each image's program
    full_ll = jax.jit(lambda zs, obs: jax.vmap(lambda p: core.log_likelihood(p, obs))(zs))
    prior_of = jax.jit(lambda zs, row: jax.vmap(lambda p: log_prior(p, row))(zs))
    coarse_lls = {}
    for shot in chosen:
        image = dataset.image(shot)
        window = core.window_for(image, tuple(config.window))
        observation = core.observe(image, window, outside_window(config))
        coarse, coarse_obs = coarse_view(core, observation, image, config.coarse)
        run = sample_smc(core, core.observe(image), config)     # picks the same window itself
        rows = run.particles.rows
        best = int(np.argmax(rows.log_evidence))
        row = int(rows.index[best])
        z = jnp.asarray(rows.state.position[best])                      # (N, d) at lambda = 1
        if coarse not in coarse_lls:
            coarse_lls[coarse] = jax.jit(lambda zs, obs, c=coarse: jax.vmap(lambda p: c.log_likelihood(p, obs))(zs))
        coarse_ll = coarse_lls[coarse]
        centred = (z - z.mean(0)) * mask
        dims = int(WALK_MASK.sum())
        cov = centred.T @ centred / (len(z) - 1) + jnp.diag(1e-8 + (1.0 - mask))
        tril = jnp.linalg.cholesky(cov) * (2.38 / np.sqrt(dims))
        key = jax.random.PRNGKey(0)
        base_full, base_coarse, base_prior = full_ll(z, observation), coarse_ll(z, coarse_obs), prior_of(z, row)
        for lam in lambdas:
            # the walk's scale for this lambda: halve until the plain walk accepts at least 20%
            scale, found = 1.0, None
            for _ in range(6):
                key, sub = jax.random.split(key)
                steps = jax.random.normal(sub, (args.proposals,) + z.shape) * mask
                proposed = (z[None] + scale * jnp.einsum("ij,pnj->pni", tril, steps)).reshape(-1, z.shape[-1])
                full = np.asarray(full_ll(proposed, observation)).reshape(args.proposals, -1) - np.asarray(base_full)
                cheap = np.asarray(coarse_ll(proposed, coarse_obs)).reshape(args.proposals, -1) - np.asarray(base_coarse)
                prior = np.asarray(prior_of(proposed, row)).reshape(args.proposals, -1) - np.asarray(base_prior)
                found = rates(np.nan_to_num(full, nan=-np.inf), np.nan_to_num(cheap, nan=-np.inf),
                              np.nan_to_num(prior, nan=-np.inf), lam, 0.25)
                if found["plain"] >= 0.2:
                    break
                scale *= 0.5
            print(f"{shot.file}: lambda {lam:.2f} scale {scale:.3f}: plain {found['plain']:.3f}, screen passes "
                  f"{found['screen']:.3f}, delayed {found['delayed']:.3f}, accepted moves per render against "
                  f"the plain walk's {found['gain']:.2f}x", flush=True)


if __name__ == "__main__":
    main()
