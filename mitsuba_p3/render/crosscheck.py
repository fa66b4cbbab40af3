"""Agreement figures between two renders of the same scene (Mitsuba vs the JAX tracer).

*Interior* pixels are those whose 3x3 neighbourhood sees one surface (object,
floor or nothing) in both renders, so silhouette pixels, where a ray may graze
either way, are excluded from the PSNR but still counted in the fraction of
pixels that differ visibly.
"""
from __future__ import annotations

from typing import Mapping

import numpy as np


def interior_mask(ids_a: np.ndarray, ids_b: np.ndarray) -> np.ndarray:
    """True where every pixel of the 3x3 neighbourhood has the centre's surface id in both."""
    ids_a, ids_b = np.asarray(ids_a), np.asarray(ids_b)
    mask = ids_a == ids_b
    height, width = ids_a.shape
    for ids in (ids_a, ids_b):
        padded = np.pad(ids, 1, mode="edge")
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                mask &= padded[1 + dy:1 + dy + height, 1 + dx:1 + dx + width] == ids
    return mask


def agreement(image_a: np.ndarray, image_b: np.ndarray, ids_a: np.ndarray, ids_b: np.ndarray) -> dict[str, float]:
    """PSNR over interior pixels, share of pixels differing by > 2/255, and more."""
    diff = np.abs(np.asarray(image_a, np.float64) - np.asarray(image_b, np.float64))
    interior = interior_mask(ids_a, ids_b)
    mse = float(np.mean(diff[interior] ** 2)) if interior.any() else float("nan")
    return {
        "psnr_interior_db": float("inf") if mse == 0 else 10 * np.log10(1.0 / mse),
        "fraction_over_2_255": float(np.mean(diff.max(axis=2) > 2 / 255)),
        "interior_fraction": float(interior.mean()),
        "surface_id_agreement": float(np.mean(np.asarray(ids_a) == np.asarray(ids_b))),
        "max_abs_difference": float(diff.max()),
        "mean_abs_difference": float(diff.mean()),
    }


def crosscheck(scene, params: Mapping[str, np.ndarray] | None = None, height: int | None = None,
               width: int | None = None, shadows: bool | None = None) -> tuple[dict, np.ndarray, np.ndarray]:
    """Render ``scene`` (unbatched) with both renderers; returns (figures, mitsuba image, jax image)."""
    from . import make_renderer

    renders = {}
    for kind in ("mitsuba", "jax"):
        renderer = make_renderer(scene, kind, height=height, width=width, shadows=shadows)
        renders[kind] = (renderer.render(params), renderer.surface_ids(params))
    figures = agreement(renders["mitsuba"][0], renders["jax"][0], renders["mitsuba"][1], renders["jax"][1])
    return figures, renders["mitsuba"][0], renders["jax"][0]


def difference_image(image_a: np.ndarray, image_b: np.ndarray, gain: float = 10.0) -> np.ndarray:
    """The two renders side by side with their absolute difference (times ``gain``)."""
    diff = np.clip(np.abs(image_a - image_b) * gain, 0.0, 1.0)
    return np.concatenate([image_a, image_b, diff], axis=1)
