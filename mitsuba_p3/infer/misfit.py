"""How much of the object the best Phong render leaves unexplained: the material kind's witness.

The benchmarks' rubber is a rough plastic (a diffuse body under a rough dielectric coat) and
their metal a rough conductor that mirrors the floor and the dark sky, tinted by its colour.
The inference model is Phong: an ambient and a diffuse term in the object's colour plus a white
specular lobe. Phong explains a rubber almost to the noise; it cannot make a metal's mirrored
surroundings, so a metal's posterior settles on some flat, dim compromise whose medians (k_a, k_d,
k_s, alpha) say little, and a gray metal sphere's compromise looks like a dark gray rubber. What *does* tell them apart is how much is left over.

:func:`phong_misfit` measures it at a posterior's pose estimate. On the object's pixels the image
is linear in the material given the pose, the class and the shininess (the renderer's material
bases: I = c k_a A + c k_d D + k_s S), so the best Phong material is a non-negative least-squares
fit of seven numbers (c k_a and c k_d per channel, k_s) for each shininess of a short grid. The
misfit is the RMS residual per channel of the best of them, over the object's pixels, in units of
the fitted noise model's residual RMS (the train renders' own misfit), so that it reads the same
on a dark set and a bright one. On the test posteriors of fsclvr, room and dark at 120x160:
rubbers 1.2-3.7 (medians 1.8-2.0), metals 0.9-8.6 (medians 3.2-4.1).

Non-negative, not ordinary, least squares: the fit stands for a render Phong could make. A pose
estimate off the object inflates the misfit of either kind alike; the rule that reads it is learnt
from train posteriors, which err the same way.
"""
from __future__ import annotations

import numpy as np

# Phong exponents the best fit chooses from (the fitted materials' shininess spans about 2-100).
SHININESS_GRID = (2.0, 4.0, 8.0, 16.0, 32.0, 64.0, 128.0)


def phong_misfit(renderer, observed: np.ndarray, pose: dict, noise_rms: float) -> float:
    """The RMS residual per channel, over the object's pixels, of the best non-negative Phong
    material at ``pose`` (``shift`` (2,), ``theta``, ``scale`` (3,), ``kappa`` (class index)), divided
    by ``noise_rms``. ``renderer`` (a :class:`~mitsuba_p3.render.mitsuba.MitsubaRenderer`) renders at
    the size of ``observed`` (H, W, 3). 1.0 when the object covers no pixel: nothing is unexplained."""
    from scipy.optimize import nnls

    observed = np.asarray(observed, np.float64)
    if observed.shape[:2] != (renderer.height, renderer.width):
        raise ValueError(f"the image is {observed.shape[:2]}, the renderer renders "
                         f"{(renderer.height, renderer.width)}")
    if not noise_rms > 0:
        raise ValueError(f"noise_rms must be positive; got {noise_rms}")
    n = len(SHININESS_GRID)
    params = {"shift": np.tile(np.asarray(pose["shift"], np.float32), (n, 1)),
              "theta": np.full(n, float(pose["theta"]), np.float32),
              "scale": np.tile(np.asarray(pose["scale"], np.float32), (n, 1)),
              "kappa": np.full(n, int(pose["kappa"]), np.int32),
              "shininess": np.asarray(SHININESS_GRID, np.float32)}
    bases = np.asarray(renderer.render_bases(params), np.float64)            # (n, H, W, 4, 3)
    mask = bases[0, :, :, :2, :].sum(axis=(-1, -2)) > 1e-6                    # the object's pixels (A or D lit)
    pixels = int(mask.sum())
    if pixels == 0:
        return 1.0
    best = np.inf
    for k in range(n):
        ambient, diffuse, specular, floor = (bases[k][mask][:, i, :] for i in range(4))   # (pixels, 3) each
        design = np.zeros((3, pixels, 7))
        for c in range(3):
            design[c, :, c], design[c, :, 3 + c], design[c, :, 6] = ambient[:, c], diffuse[:, c], specular[:, c]
        target = (observed[mask] - floor).T.reshape(-1)                      # channel-major, like the design
        _, residual = nnls(design.reshape(3 * pixels, 7), target)
        best = min(best, residual ** 2)
    return float(np.sqrt(best / (3 * pixels)) / noise_rms)


def model_misfit(fitted, observed: np.ndarray, pose: dict, renderer=None) -> float:
    """:func:`phong_misfit` under a fitted model: its scene rendered with the shadows of its noise
    model, in units of that model's residual RMS. Pass ``renderer`` (from an earlier call's
    ``misfit_renderer``) to score many posteriors of one data set without building it again."""
    noise = fitted.noise
    renderer = renderer or misfit_renderer(fitted, *np.asarray(observed).shape[:2])
    return phong_misfit(renderer, observed, pose, noise.gaussian_sigma or noise.sigma)


def misfit_renderer(fitted, height: int, width: int):
    """The renderer :func:`model_misfit` uses for images of ``height`` x ``width``."""
    from ..render import make_renderer

    return make_renderer(fitted.scene(), "mitsuba", height=height, width=width, shadows=fitted.noise.shadows)
