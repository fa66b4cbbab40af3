"""Material refinement after gradient descent: exact least squares on the material bases.

Adam with one learning rate moves a material's shininess and specular weight
very little: the highlight covers a few pixels of a whole-image loss, so their
gradients are small and noisy, and the fitted metals stay where they started
(flat ambient colours). But at a fixed pose and shininess alpha the Phong image
of an object is affine in its material (:meth:`~mitsuba_p3.render.mitsuba.MitsubaRenderer.render_bases`):

    I = c (k_a A + k_d D) + k_s S + F

so every material of the train split is refitted exactly, for each alpha of a
log-spaced grid, by alternating least squares over all of its images: the
weights (k_a, k_d, k_s) given the colour c (a 3-unknown linear problem), then
the colour given the weights (per channel, one unknown), the weights by
non-negative least squares with a small ridge, the colour clipped to [0, 1]. The alpha with the least
squared error (after clipping to [0, 1], as the renderer does) is kept.
"""
from __future__ import annotations

import numpy as np

from ..space import OBJECT_KEYS

SHININESS_GRID = (1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0, 256.0)


def _ridge_nnls(design: np.ndarray, target: np.ndarray, ridge: float = 1e-4) -> np.ndarray:
    """Non-negative least squares with a small ridge: a basis that is (nearly) zero, such as the
    specular light sum at a shininess whose highlight no pixel sees, gets weight 0, not an
    arbitrary one. The ridge is ``ridge`` times the mean squared column norm."""
    from scipy.optimize import nnls

    gram = design.T @ design
    strength = ridge * np.trace(gram) / len(gram)
    # the normal equations with the ridge, as an NNLS problem via their Cholesky factor
    factor = np.linalg.cholesky(gram + strength * np.eye(len(gram)))
    rhs = np.linalg.solve(factor, design.T @ target)
    return nnls(factor.T, rhs)[0]


def fit_material(images: np.ndarray, bases: np.ndarray, colour: np.ndarray, iterations: int = 8) -> tuple[dict, float]:
    """Alternating least squares for one material at one shininess.

    ``images`` (n, H, W, 3) and their ``bases`` (n, H, W, 4, 3) = (A, D, S, F); ``colour`` starts the
    alternation. Returns the material (colour, ambient, diffuse, specular) and its squared error."""
    A, D, S, F = (bases[..., i, :].reshape(-1, 3).astype(np.float64) for i in range(4))
    y = images.reshape(-1, 3).astype(np.float64) - F
    c = np.clip(np.asarray(colour, np.float64), 1e-3, 1.0)
    weights = np.zeros(3)
    for _ in range(iterations):
        design = np.stack([(c * A).ravel(), (c * D).ravel(), S.ravel()], axis=1)
        weights = _ridge_nnls(design, y.ravel())
        k_a, k_d, k_s = weights
        slope = k_a * A + k_d * D
        c = np.clip(np.sum(slope * (y - k_s * S), axis=0) / np.maximum(np.sum(slope * slope, axis=0), 1e-12),
                    0.0, 1.0)
    k_a, k_d, k_s = weights
    predicted = np.clip(c * (k_a * A + k_d * D) + k_s * S + F, 0.0, 1.0)
    error = float(np.sum((predicted - (y + F)) ** 2))
    return {"colour": c, "ambient": k_a, "diffuse": k_d, "specular": k_s}, error


def refine_materials(renderer, images: dict[str, np.ndarray], params: dict[str, list[dict]],
                     materials: dict[str, dict], grid=SHININESS_GRID) -> tuple[dict[str, dict], dict[str, float]]:
    """Refit every material (key -> its images (n, H, W, 3) and their contract parameters, geometry and
    globals included) over the shininess ``grid`` and the material's current shininess; returns the
    refined materials (colour, ambient, diffuse, specular, shininess) and each one's squared error."""
    refined, errors = {}, {}
    for key, start in materials.items():
        # the current shininess first: another must lower the error by more than a hair to replace it
        # (with no highlight in view every shininess fits alike, and the prior should not learn a random one)
        best = None
        for alpha in [float(start["shininess"])] + sorted(set(grid) - {float(start["shininess"])}):
            # one batched render of every image of the material: object parameters stacked, globals shared
            batch = {name: (np.stack([np.asarray(p[name]) for p in params[key]]) if name in OBJECT_KEYS else value)
                     for name, value in params[key][0].items()}
            batch["shininess"] = np.full(len(params[key]), alpha, np.float32)
            bases = renderer.render_bases(batch)
            material, error = fit_material(images[key], bases, np.asarray(start["colour"]))
            if best is None or error < best[1] * (1.0 - 1e-4):
                best = ({**material, "shininess": alpha}, error)
        refined[key] = {name: (np.asarray(v).tolist() if name == "colour" else float(v))
                        for name, v in best[0].items()}
        errors[key] = best[1]
    return refined, errors
