"""A coarse view of one image's likelihood: the same scene scored at 1 / f of the resolution.

The SMC's first temperatures choose where the object is; the likelihood there is raised to a
small lambda, so its fine detail barely counts, and a wide start (many particles while the pose
is chosen) pays for every pixel of every particle. Scored on a box-averaged image at a 1 / f
grid, a render has f^2 times fewer pixels, so f^2 times the particles cost what the full
resolution's first steps cost.

The coarse likelihood is the full one's noise model with its precision (power / sigma^2) multiplied
by f^2: f^2 fewer pixels at f^2 the precision keep about the same total evidence, whether the
residual is correlated over many pixels (a box is about as variable as one pixel; the fitted power
1 / correlation area rises f^2-fold) or white (a box mean's variance is sigma^2 / f^2; at power 1
sigma falls f-fold), so the particles the coarse steps leave are near where the full likelihood
wants them, and the change's weights stay even. Nothing else
depends on it being right: the SMC reweights by the ratio of the two tempered likelihoods where
it changes from the coarse target to the full one (:func:`to_full`), so its
evidence estimates the full likelihood's, whatever the coarse one is.

It is P3's colour likelihood even for NP3 (VGG16's features of a 28 x 36 window mean little). The
spectral noise form has no spectrum fitted at the coarse size, and an image whose size is not a
multiple of f has no exact box grid: their wide start runs at the full resolution.
"""
from __future__ import annotations

from dataclasses import replace

import numpy as np


def downsample(image: np.ndarray, factor: int) -> np.ndarray:
    """(H, W, C) -> (H / f, W / f, C): the mean of each f x f box (H and W multiples of f)."""
    height, width = image.shape[:2]
    boxes = np.asarray(image, np.float32).reshape(height // factor, factor, width // factor, factor, -1)
    return boxes.mean(axis=(1, 3))


def coarse_view(core, observation: dict, image: np.ndarray, factor: int):
    """(coarse core, coarse observation) of ``observation`` (a window of the whole ``image``, or all
    of it) at 1 / ``factor`` of ``core``'s resolution; None (score at the full resolution) under the
    spectral noise form or where the image's size is not a multiple of ``factor``."""
    from .model import PosteriorCore

    height, width = core.renderer.height, core.renderer.width
    if core.config.spectral or height % factor or width % factor or np.shape(image)[:2] != (height, width):
        return None
    power = min(1.0, core.config.power * factor ** 2)
    sigma = core.config.sigma * np.sqrt(power / (core.config.power * factor ** 2))
    # (the image's own scale is bridged in after the search, mitsuba_p3.infer.smc: the coarse start scores without it)
    likelihood = replace(core.config, kind="p3", power=power, sigma=float(sigma), scale=None)
    coarse = PosteriorCore.shared(core.fitted, likelihood, core.renderer_kind, height // factor, width // factor)
    small = downsample(image, factor)
    if "window" not in observation:
        return coarse, coarse.observe(small)
    top, left = (int(v) // factor for v in observation["window"])
    rows, cols = (max(8, n // factor) for n in np.shape(observation["image"])[:2])
    top, left = min(top, height // factor - rows), min(left, width // factor - cols)
    return coarse, coarse.observe(small, (top, left, rows, cols), float(observation["outside_window"]))


def to_full(kernels, state, index, observation):
    """A coarse start's particles scored by the full likelihood (``kernels``' score of ``observation``) at
    the same lambda: the state with the full log likelihoods, and each particle's log weight lambda (full -
    coarse) for the step that changes targets, so that its evidence stays the full likelihood's."""
    import jax.numpy as jnp

    fine, _ = kernels.score(jnp.asarray(state.position), index, observation)
    fine = np.asarray(fine, np.float64)
    change = state.tempering[:, None] * (fine - state.loglikelihood)
    return state._replace(loglikelihood=fine.astype(np.float32)), change
