"""Adaptive Metropolis tuning: the walk covariance, the modes' means and the step-size factor.

After each tuning round the walk becomes a full-covariance Gaussian (Haario et
al. 2001): the within-mode covariance of recent draws, pooled over modes, times
2.38^2 / d, times a factor corrected towards the target acceptance rate. The
modes' means are the targets of the mode jumps (:mod:`.mcmc`).
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np


class Proposal(NamedTuple):
    """The walk covariance and the modes' means, learnt during tuning (see the module docstring)."""
    tril: np.ndarray              # (d, d) lower Cholesky factor of the walk covariance
    means: np.ndarray             # (modes, d)
    known: np.ndarray             # (modes,) bool: the mode held enough draws to jump to it

    @classmethod
    def isotropic(cls, scale: float, mask: np.ndarray, modes: int) -> "Proposal":
        d = len(mask)
        return cls(np.diag(scale * mask).astype(np.float32), np.zeros((modes, d), np.float32), np.zeros(modes, bool))


def learn_proposal(positions: np.ndarray, labels: np.ndarray, modes: int, mask: np.ndarray, factor: float,
                   min_share: float = 0.01) -> Proposal:
    """The walk covariance and the modes' means from tuning draws (n, d) and their mode labels (n,).

    The walk covariance is the within-mode covariance pooled over modes (the spread
    between modes is the jumps' business), scaled by 2.38^2 / d (Haario et al.
    2001) and the tuned ``factor``. A mode holding >= ``min_share`` of the draws is
    *known* (a jump target)."""
    dimension = positions.shape[1]
    counts = np.bincount(labels, minlength=modes)
    means = np.zeros((modes, dimension))
    scatter = np.zeros((dimension, dimension))
    for m in np.flatnonzero(counts):
        members = positions[labels == m]
        means[m] = members.mean(axis=0)
        scatter += (members - means[m]).T @ (members - means[m])
    covariance = scatter / max(len(positions) - len(np.flatnonzero(counts)), 1) + 1e-8 * np.eye(dimension)
    walked = mask > 0
    tril = np.zeros((dimension, dimension), np.float32)
    tril[np.ix_(walked, walked)] = (np.linalg.cholesky(covariance[np.ix_(walked, walked)])
                                    * 2.38 / np.sqrt(walked.sum()) * factor)
    known = counts >= max(2, min_share * len(positions))
    return Proposal(tril, means.astype(np.float32), known)


def acceptance_correction(acceptance: float, target: float, tolerance: float = 0.05) -> float:
    """Factor for the proposal scale that moves a random walk's acceptance rate to ``target``.

    For a random walk in many dimensions the acceptance rate is about
    2 Phi(-l sqrt(I) / 2) for a step length l (Roberts, Gelman and Gilks 1997), so l
    scales with Phi^-1(rate / 2); the correction is the ratio of those quantiles,
    limited to [1/4, 4] per round, and 1 within ``tolerance`` of the target. The
    target 0.25 is near the optimal 0.234 and well inside the 20-50% band."""
    from scipy.stats import norm

    if abs(acceptance - target) <= tolerance:
        return 1.0
    ratio = norm.ppf(target / 2) / norm.ppf(np.clip(acceptance, 0.005, 0.95) / 2)
    return float(np.clip(ratio, 0.25, 4.0))


def move_statistics(moves: np.ndarray) -> dict:
    """Acceptance rates from per-step move records (..., 4): see ``_block_runner``."""
    moves = moves.reshape(-1, 4).sum(axis=0)
    walk_accepted, walk_proposed, jump_accepted, jump_proposed = moves
    return {"walk_acceptance": float(walk_accepted / max(walk_proposed, 1)),
            "jump_acceptance": float(jump_accepted / max(jump_proposed, 1)),
            "jumps_accepted": int(jump_accepted)}
