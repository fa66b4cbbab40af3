"""The parameter space Omega of one object, and its unconstrained coordinates z.

Every stage that talks about "a point" of the model uses this layout: the fit
builds priors over it, the sampler walks in it, the plots label its axes.

=========  =====  ==========================================================
variable   dims   meaning
=========  =====  ==========================================================
shift      2      position (x, y) of the object on the floor, metres
theta      1      yaw about the vertical axis, radians
scale      3      half-extents (sx, sy, sz), metres
kappa      2      logits of the shape class (the third logit is fixed at 0)
colour     3      RGB albedo
ambient    1      k_a
diffuse    1      k_d
specular   1      k_s
shininess  1      alpha
=========  =====  ==========================================================

The bijectors between z and the natural values live with the prior
(:class:`mitsuba_p3.fit.priors.Prior`), because they are fitted to the data.
This module says only where each variable sits in z (:data:`SLICES`), how
natural values become the renderer contract's object parameters
(:func:`render_params`), and which *discrete hypothesis* a point belongs to:
its shape class times its material kind (:func:`hypothesis_of`).
"""
from __future__ import annotations

import numpy as np

from .shapes import SHAPES

# Layout of the unconstrained vector z.
SLICES: dict[str, slice] = {
    "shift": slice(0, 2), "theta": slice(2, 3), "scale": slice(3, 6), "kappa": slice(6, 8),
    "colour": slice(8, 11), "ambient": slice(11, 12), "diffuse": slice(12, 13),
    "specular": slice(13, 14), "shininess": slice(14, 15),
}
DIMENSION = 15
# The material variables (priors fitted as Gaussian mixtures to the optimised materials).
MATERIAL_VARIABLES = ("colour", "ambient", "diffuse", "specular", "shininess")
# The renderer contract's object parameters, in the order the Mitsuba callback passes them.
OBJECT_KEYS = ("shift", "theta", "scale", "kappa", "colour", "ambient", "diffuse", "specular", "shininess")
# Material kinds: matte (specular weight in the prior's low component) or shiny.
MATERIAL_KINDS = ("matte", "shiny")
# A discrete hypothesis is a shape class times a material kind: index = class * 2 + kind.
HYPOTHESES = tuple(f"{shape}/{kind}" for shape in SHAPES for kind in MATERIAL_KINDS)


def coordinate_names() -> list[str]:
    """One name per coordinate of z: shift_0, shift_1, theta_0, ..."""
    return [f"{name}_{i}" for name, s in SLICES.items() for i in range(s.stop - s.start)]


def hypothesis_of(z, specular_threshold: float, xp=np):
    """The discrete hypothesis (int) of positions z (..., 15): class * 2 + (z_specular > threshold).

    ``specular_threshold`` is the unconstrained specular value between the prior's
    two specular components (:meth:`mitsuba_p3.fit.priors.Prior.specular_threshold`);
    ``xp`` is ``numpy`` or ``jax.numpy``."""
    k = SLICES["kappa"].start
    logits = xp.stack([z[..., k], z[..., k + 1], xp.zeros_like(z[..., k])], axis=-1)
    shiny = (z[..., SLICES["specular"].start] > specular_threshold).astype(xp.int32)
    return xp.argmax(logits, axis=-1).astype(xp.int32) * len(MATERIAL_KINDS) + shiny


def render_params(x: dict, xp=np) -> dict:
    """Natural values (batched or not) -> the renderer contract's object parameters.

    The class is the argmax of the relaxed one-hot; colours are clipped to [0, 1],
    Phong weights to >= 0 and the shininess to >= 1 (the GMMs have unbounded support).
    ``xp`` is ``numpy`` or ``jax.numpy`` (inside the sampler).
    """
    f32 = lambda v: xp.asarray(v, xp.float32)  # noqa: E731
    return {
        "shift": f32(x["shift"]), "theta": f32(x["theta"]), "scale": f32(x["scale"]),
        "kappa": xp.argmax(xp.asarray(x["class_probabilities"]), axis=-1).astype(xp.int32),
        "colour": xp.clip(f32(x["colour"]), 0.0, 1.0),
        "ambient": xp.maximum(f32(x["ambient"]), 0.0), "diffuse": xp.maximum(f32(x["diffuse"]), 0.0),
        "specular": xp.maximum(f32(x["specular"]), 0.0), "shininess": xp.maximum(f32(x["shininess"]), 1.0),
    }
