"""How far and along what the SMC's pose moves step: the walked dimensions and each row's proposal scales.

The random walk and the gradient move of :mod:`mitsuba_p3.infer.smc_moves` take their shapes from the
particles themselves: a row's walk proposes with 2.38^2 / d times its particles' covariance over the
walked dimensions (the optimal scaling of Gelman, Roberts and Gilks 1996, times the row's adapted
``scale``), and its MALA step is preconditioned by the Cholesky factor of their covariance over the pose.
These are computed from the resampled particles before each move: on the host with numpy (in float64),
or on the device inside the step's compiled call (:mod:`mitsuba_p3.infer.device_step`) with ``jax.numpy``.
"""
from __future__ import annotations

import numpy as np

from ..space import DIMENSION, SLICES

# what the random walk moves: not the class (fixed by the hypothesis) nor the material (the material update's)
WALK_MASK = np.array([0.0 if any(i in range(DIMENSION)[SLICES[name]]
                                 for name in ("kappa", "colour", "ambient", "diffuse", "specular")) else 1.0
                      for i in range(DIMENSION)], np.float32)


# what the gradient move moves: position, yaw and log half-extents
POSE_MASK = np.array([1.0 if any(i in range(DIMENSION)[SLICES[name]] for name in ("shift", "theta", "scale"))
                      else 0.0 for i in range(DIMENSION)], np.float32)


def covariance_factors(position, mask: np.ndarray, xp=np):
    """Each row's Cholesky factor (R, d, d) of its particles' covariance (R, N, d) over the dimensions of
    ``mask`` (plus 1e-6 on their diagonal; zero elsewhere). ``xp``: numpy (in float64) or ``jax.numpy``."""
    from .. import small_linalg

    moved = np.flatnonzero(mask > 0)
    x = (np.asarray(position, np.float64) if xp is np else position)[..., moved]
    centred = x - x.mean(axis=1, keepdims=True)
    cov = xp.einsum("rni,rnj->rij", centred, centred) / (x.shape[1] - 1) + 1e-6 * xp.eye(len(moved))
    embed = xp.asarray(np.eye(DIMENSION)[:, moved], x.dtype)        # (d, k): the k dimensions into all d
    return xp.einsum("ik,rkl,jl->rij", embed, small_linalg.cholesky(cov, xp), embed)


def walk_factors(position, scale, xp=np):
    """Each row's walk Cholesky factor (R, d, d), float32: 2.38 / sqrt(d) times its particles' covariance
    over the walked dimensions, times its ``scale``."""
    factors = covariance_factors(position, WALK_MASK, xp) * 2.38 / np.sqrt(int(WALK_MASK.sum()))
    return (factors * xp.asarray(scale)[:, None, None]).astype(np.float32)


def pose_directions(position: np.ndarray) -> np.ndarray:
    """Each row's gradient-move directions (R, d, k): the columns of the Cholesky factor of its
    particles' covariance over the k pose dimensions (:data:`POSE_MASK`)."""
    return covariance_factors(position, POSE_MASK)[:, :, POSE_MASK > 0].astype(np.float32)


def gradient_step(scale: np.ndarray) -> np.ndarray:
    """(R,) the gradient move's step in the whitened coordinates: MALA's optimal 1.65 k^(-1/3)
    (Roberts and Rosenthal 1998) times each row's adapted scale."""
    return (1.65 * float(POSE_MASK.sum()) ** (-1.0 / 3.0) * np.asarray(scale)).astype(np.float32)
