"""How far and along what the SMC's pose moves step: the walked dimensions and each row's proposal scales.

The random walk and the gradient move of :mod:`mitsuba_p3.infer.smc_moves` take their shapes from the
particles themselves: a row's walk proposes with 2.38^2 / d times its particles' covariance over the
walked dimensions (the optimal scaling of Gelman, Roberts and Gilks 1996, times the row's adapted
``scale``), and its MALA step is preconditioned by the Cholesky factor of their covariance over the pose.
These are computed on the host from the resampled particles before each move.
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


def covariance_factors(position: np.ndarray, mask: np.ndarray) -> np.ndarray:
    """Each row's Cholesky factor (R, d, d) of its particles' covariance over the dimensions of
    ``mask`` (zero elsewhere)."""
    moved = mask > 0
    tril = np.zeros((len(position), DIMENSION, DIMENSION))
    for r in range(len(position)):
        cov = np.cov(position[r][:, moved], rowvar=False) + 1e-6 * np.eye(moved.sum())
        tril[r][np.ix_(moved, moved)] = np.linalg.cholesky(cov)
    return tril


def walk_factors(position: np.ndarray, scale: np.ndarray) -> np.ndarray:
    """Each row's walk Cholesky factor (R, d, d): 2.38 / sqrt(d) times its particles' covariance
    over the walked dimensions, times its ``scale``."""
    factors = covariance_factors(position, WALK_MASK) * 2.38 / np.sqrt(int(WALK_MASK.sum()))
    return (factors * np.asarray(scale)[:, None, None]).astype(np.float32)


def pose_directions(position: np.ndarray) -> np.ndarray:
    """Each row's gradient-move directions (R, d, k): the columns of the Cholesky factor of its
    particles' covariance over the k pose dimensions (:data:`POSE_MASK`)."""
    return covariance_factors(position, POSE_MASK)[:, :, POSE_MASK > 0].astype(np.float32)


def gradient_step(scale: np.ndarray) -> np.ndarray:
    """(R,) the gradient move's step in the whitened coordinates: MALA's optimal 1.65 k^(-1/3)
    (Roberts and Rosenthal 1998) times each row's adapted scale."""
    return (1.65 * float(POSE_MASK.sum()) ** (-1.0 / 3.0) * np.asarray(scale)).astype(np.float32)
