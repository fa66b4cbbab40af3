"""Light from the whole environment, as two hemispheres: the sky above the horizon, the ground below.

Point lights light a surface only from a few directions. A path tracer's scene also lights it from
everywhere else: the sky (or the room) above, the lit floor below. A metal shows this most: its lower
half mirrors the floor and its upper half the sky, which no highlight at a point light can make. The
Phong model's ambient term is the crudest answer, one constant for every normal. The hemisphere term
is the next one: an environment of radiance ``sky`` above the horizon and ``ground`` below it, both
fitted on the train split with the lights (``mitsuba-p3 fit --observation hemisphere``).

With the model's own lobes, and no occlusion by the object itself, a surface of normal n seen from
direction v receives

    diffuse:   H_d(n) = ground + (sky - ground) (1 + n_z) / 2

the exact irradiance (over pi) from a uniform sky and ground split at the horizon, and reflects

    specular:  H_s(r, alpha) = 2 pi / (alpha + 2) [ground + (sky - ground) Phi(e(r) sqrt(alpha + 2))]

where r = 2 (n.v) n - v is the mirror direction, e(r) = asin(r_z) its elevation, 2 pi / (alpha + 2)
the solid angle of the Phong lobe max(0, r.l)^alpha (times the cosine, to first order) and Phi the
normal distribution function: the share of a lobe of angular width about 1 / sqrt(alpha + 2) that
lies above the horizon. Both terms join the light sums D and S of the Phong model, so the image stays
``c (k_a A + k_d D) + k_s S`` and affine in the materials (the samplers' material update is
unchanged). With sky = ground = 0 they vanish and the model is the paper's.

The functions take an array module ``xp`` with ``sqrt``, ``arcsin``/``asin``, ``clip`` and an ``erf``
so that the Mitsuba renderer (Dr.Jit), the JAX tracer and numpy share one formula.
"""
from __future__ import annotations

import math

SQRT_HALF = math.sqrt(0.5)


def diffuse_term(normal_z, sky, ground):
    """H_d: irradiance / pi from the two hemispheres at a normal of height ``normal_z``."""
    return ground + (sky - ground) * ((1.0 + normal_z) * 0.5)


def specular_term(reflected_z, shininess, sky, ground, asin, erf, sqrt, clip):
    """H_s: the Phong lobe about the mirror direction (height ``reflected_z``) over the two hemispheres
    (alpha < 0 reads as 0, as in every lobe: :func:`~mitsuba_p3.render.lobes.sharpness`)."""
    from .lobes import sharpness

    shininess = sharpness(shininess)
    width = sqrt(shininess + 2.0)
    elevation = asin(clip(reflected_z, -1.0, 1.0))
    above = 0.5 * (1.0 + erf(elevation * width * SQRT_HALF))
    return (2.0 * math.pi / (shininess + 2.0)) * (ground + (sky - ground) * above)
