"""The evidence of a finished run, by importance sampling from its own particles.

A tempered SMC run estimates log Z_h as the sum, over its temperatures, of the log mean incremental
weight. Every term carries the particles of its moment, so the estimate's error is the path's: two runs
of one hypothesis that end at the same optimum can still estimate its evidence several nats apart, the
later one to find the optimum lower. Once a run has
reached lambda = 1, its final particles show where its posterior lies, and an importance-sampling
estimate from a proposal q fitted to them,

    Z_h ~= (1 / M) sum_m p(z_m | h) L(z_m) / q(z_m),    z_m ~ q,

is unbiased for any q that covers the posterior, whatever path led there; its error is how far q is from
the posterior, not how the run got there. q is fitted to the run's own particles only, so the runs of a
hypothesis stay independent: runs that found one optimum agree to the importance weights' error, and a
run that settled on a worse optimum, whose q covers only that one, still estimates low (the island gap
shows a search failure as before).

**The proposal.** Every primitive is the same shape a quarter turn later (:mod:`~mitsuba_p3.infer.symmetry`),
so a posterior has four copies of each pose. The run's particles are folded into its chart (one copy),
a multivariate Student-t (``dof``) is fitted there to their mean and covariance (the class logits, fixed
within a hypothesis, left out), and each draw is turned into a copy chosen uniformly: q is the mixture of
the four turned t's, its density summed over the four turns back (with the turn's Jacobian in the
logistic yaw coordinate). Its heavy tails keep the weights bounded far from the particles, where a
Gaussian fitted to them would not.

**The estimate a run keeps** is the mean of the two unbiased estimates, (Z_SMC + Z_IS) / 2, again
unbiased: where the importance weights degenerate (a run whose particles collapsed onto a few points, or
whose posterior is not one bump in the chart) the tempered estimate carries it, and where the path's
error put the tempered estimate low the importance estimate does. Either failing costs at most log 2.

Cost: ``draws`` renders per run, scored in one batched call for all runs with the run's own kernels
(:func:`~mitsuba_p3.infer.smc_moves.kernels`' ``score``).
"""
from __future__ import annotations

from typing import Callable, NamedTuple

import numpy as np
from scipy import linalg, special

from ..space import DIMENSION, SLICES
from .symmetry import chart_centres, folded, quarter_turn

# the coordinates the proposal spans: all but the class logits, which a hypothesis fixes
FREE = np.array([i for i in range(DIMENSION) if not SLICES["kappa"].start <= i < SLICES["kappa"].stop])
# the proposal's degrees of freedom (chosen on train posteriors; a range of values does alike)
DOF = 5.0
# added to the fitted covariance's diagonal, so that particles collapsed onto one point still give a density
JITTER = 1e-6
COPIES = 4


class Proposal(NamedTuple):
    """One Student-t per run in its chart's free coordinates: mean (R, d), Cholesky factor of the scale
    (R, d, d), degrees of freedom; ``template`` (R, 15) gives the coordinates the t leaves fixed."""
    mean: np.ndarray
    chol: np.ndarray
    dof: float
    template: np.ndarray


class Estimate(NamedTuple):
    """Per run (R,): the importance-sampling log evidence, its weights' effective sample size, and the
    log evidence a run keeps (the log mean of the tempered and the importance estimate's Z)."""
    importance: np.ndarray
    ess: np.ndarray
    log_evidence: np.ndarray


def fit(position: np.ndarray, dof: float = DOF) -> Proposal:
    """The proposal of each run (row) of ``position`` (R, N, 15): a Student-t fitted to the row's particles
    folded into its symmetry chart."""
    position = np.asarray(position, np.float64)
    chart = folded(position, chart_centres(position))
    free = chart[..., FREE]
    mean = free.mean(axis=1)
    centred = free - mean[:, None]
    cov = np.einsum("rni,rnj->rij", centred, centred) / max(position.shape[1] - 1, 1)
    chol = np.linalg.cholesky(cov + JITTER * np.eye(len(FREE)))
    return Proposal(mean, chol, float(dof), chart[:, 0].copy())


def _t_logpdf(x: np.ndarray, mean: np.ndarray, chol: np.ndarray, dof: float) -> np.ndarray:
    """log density (M,) of one multivariate Student-t (location ``mean``, scale ``chol chol^T``) at x (M, d)."""
    d = x.shape[-1]
    u = linalg.solve_triangular(chol, (x - mean).T, lower=True)
    maha = np.sum(u * u, axis=0)
    return (special.gammaln((dof + d) / 2) - special.gammaln(dof / 2) - d / 2 * np.log(dof * np.pi)
            - np.sum(np.log(np.diag(chol))) - (dof + d) / 2 * np.log1p(maha / dof))


def log_density(proposal: Proposal, z: np.ndarray) -> np.ndarray:
    """log q (R, M) of positions z (R, M, 15): each row's t summed over the four turns back into its chart."""
    z = np.asarray(z, np.float64)
    rows, count = z.shape[:2]
    out = np.empty((rows, count))
    for r in range(rows):
        terms = []
        for k in range(COPIES):
            back, log_jacobian = quarter_turn(z[r], np.full(count, -k))
            terms.append(_t_logpdf(back[:, FREE], proposal.mean[r], proposal.chol[r], proposal.dof) + log_jacobian)
        out[r] = special.logsumexp(np.stack(terms), axis=0) - np.log(COPIES)
    return out


def draw(proposal: Proposal, rng: np.random.Generator, count: int) -> np.ndarray:
    """(R, count, 15) draws of each row's proposal: a t draw in the chart, turned into a uniform copy."""
    rows, d = proposal.mean.shape
    gauss = np.einsum("rij,rmj->rmi", proposal.chol, rng.standard_normal((rows, count, d)))
    radial = np.sqrt(rng.chisquare(proposal.dof, (rows, count)) / proposal.dof)
    z = np.repeat(proposal.template[:, None], count, axis=1)
    z[..., FREE] = proposal.mean[:, None] + gauss / radial[..., None]
    return quarter_turn(z, rng.integers(COPIES, size=(rows, count)))[0]


def importance_evidence(score: Callable, index: np.ndarray, position: np.ndarray, tempered: np.ndarray,
                        observation, rng: np.random.Generator, draws: int, dof: float = DOF) -> Estimate:
    """Each run's (row's) importance-sampling log evidence from ``draws`` draws of a proposal fitted to its
    final particles ``position`` (R, N, 15), and the log evidence it keeps beside its ``tempered`` (R,)
    estimate. ``score(z (R, M, 15), index (R,), observation) -> (log likelihood, log prior)`` (R, M) is the
    run's own: the kernels' batched score of hypothesis ``index[r]`` on row r."""
    import jax.numpy as jnp

    proposal = fit(position, dof)
    z = draw(proposal, rng, draws)
    loglik, logprior = score(jnp.asarray(z, jnp.float32), jnp.asarray(index, jnp.int32), observation)
    # the density of the draws as the renderer saw them (float32), so that q and the target meet at one point
    log_q = log_density(proposal, np.asarray(z, np.float32))
    log_w = np.asarray(loglik, np.float64) + np.asarray(logprior, np.float64) - log_q
    log_w = np.where(np.isfinite(log_w), log_w, -np.inf)
    importance = special.logsumexp(log_w, axis=1) - np.log(draws)
    peak = np.max(log_w, axis=1, keepdims=True)
    w = np.exp(log_w - np.where(np.isfinite(peak), peak, 0.0))
    ess = np.sum(w, axis=1) ** 2 / np.maximum(np.sum(w * w, axis=1), 1e-300)
    kept = np.logaddexp(np.asarray(tempered, np.float64), importance) - np.log(2)
    return Estimate(importance, ess, kept)
