"""The specular lobe of the observation model: Phong's highlight, or a GGX microfacet lobe.

The image is ``c (k_a A + k_d D) + k_s S`` whatever the lobe: only the specular light sum

    S = sum_l I_l V_l [n.l > 0] s(l, v)

changes with it, so the samplers' material update (affine in the colour and the weights given
the shininess) and the fit's least squares are the same for both.

``phong``: s = max(0, r.v)^alpha, r the light direction mirrored about n (the paper's).

``ggx``: the Cook-Torrance reflection of a rough surface with the GGX (Trowbridge-Reitz)
distribution of microfacet normals and Smith's separable shadowing (Walter et al. 2007),
times the cosine, as Mitsuba's ``roughconductor`` evaluates it at a light:

    s = D(h) G1(l) G1(v) / (4 n.v),   h = (l + v) / |l + v|,
    D(h) = a^2 / (pi ((n.h)^2 (a^2 - 1) + 1)^2),   G1(x) = 2 n.x / (n.x + sqrt(a^2 + (1 - a^2) (n.x)^2)).

Its roughness is tied to the shininess by the usual Phong-to-microfacet correspondence
a^2 = 2 / (alpha + 2) (Walter et al. 2007: the Beckmann width whose lobe matches
max(0, n.h)^alpha near its peak), so ``shininess`` keeps its meaning as the lobe's
sharpness, and the priors, the fit's shininess grid and every sampler move are unchanged.
What the lobe changes is its shape: GGX's long tails (a rough metal's broad sheen around a
sharp core), the highlight's stretch at grazing angles (the half vector, not the mirror
direction) and the shadowing that dims it at the silhouette. Fresnel's angular factor is
left out (taken as 1, a conductor's nearly flat Fresnel): a dielectric's would need a
per-material index of refraction in the contract, its prior and the samplers' state, and
k_s absorbs its value at normal incidence.

The formula takes a ``sqrt`` so that Dr.Jit (the Mitsuba renderer and the ``phong`` BSDF)
and JAX (the tracer) share it.
"""
from __future__ import annotations

import math

from ..scene.model import LOBES, check_lobe  # noqa: F401  (the names and their check live with the scene)

# the fit's name of each lobe's observation model (``mitsuba-p3 fit --observation``)
OBSERVATION_LOBES = {"phong": "phong", "hemisphere": "phong", "microfacet": "ggx"}


def sharpness(shininess):
    """max(alpha, 0), written (alpha + |alpha|) / 2 so that Dr.Jit, JAX and numpy share it. The priors'
    Gaussian mixtures over alpha reach below 0, where neither lobe means anything (Phong's
    max(0, r.v)^alpha grows away from the mirror direction and overflows to inf, and inf times a zero
    weight is NaN; GGX would take a square root of a negative number): every lobe reads alpha through
    this, so that every point of the sampler's space renders, as the flat (alpha = 0) lobe."""
    return 0.5 * (shininess + abs(shininess))


def ggx_roughness_squared(shininess):
    """a^2 of the GGX lobe whose sharpness matches a Phong exponent: 2 / (alpha + 2); the roughest,
    a^2 = 1, for alpha <= 0 (:func:`sharpness`)."""
    return 2.0 / (sharpness(shininess) + 2.0)


def ggx_term(shininess, cos_light, cos_view, cos_half, sqrt):
    """The GGX lobe times the cosine, D G1(l) G1(v) / (4 n.v) (see the module docstring).

    ``cos_light`` = n.l and ``cos_view`` = n.v must be >= 0 (the caller masks unlit points
    and clamps n.v); written as D n.l / ((n.l + L_l)(n.v + L_v)) with L_x = sqrt(a^2 + (1 - a^2)
    (n.x)^2), which stays finite at grazing view."""
    a2 = ggx_roughness_squared(shininess)
    d = cos_half * cos_half * (a2 - 1.0) + 1.0
    distribution = a2 / (math.pi * d * d)
    reach_l = sqrt(a2 + (1.0 - a2) * cos_light * cos_light)
    reach_v = sqrt(a2 + (1.0 - a2) * cos_view * cos_view)
    return distribution * cos_light / ((cos_light + reach_l) * (cos_view + reach_v))
