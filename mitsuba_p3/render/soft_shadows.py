"""Soft shadows from point lights widened into small spheres, on a fixed pattern.

A path tracer's lights have an area, and its shadows a penumbra as wide as the
light seen from the shadow's caster; a point light casts a hard shadow. Both
renderers therefore give every light a radius r (the contract's
``light_radius``, one for all lights, fitted on the train split by
:func:`mitsuba_p3.fit.scene_opt.fit_light_radius`) and let a point see the
light through the disc of radius r facing it: the light's visibility is the
share of the disc's sample points that a shadow ray reaches. Only shadows
soften; shading still uses the light's centre, as a sphere light's would to
first order.

The sample points are a fixed Vogel (golden-angle) spiral, equal-area and well
spread, not random: a render stays a deterministic function of its
parameters, so the samplers' likelihood has no Monte Carlo noise. One sample is
the centre itself: hard shadows, exactly as before.

The disc's frame around the direction to the light is Duff et al.'s branchless
orthonormal basis ("Building an Orthonormal Basis, Revisited", JCGT 2017), the
same formula in both renderers so that their sample points agree.
"""
from __future__ import annotations

import numpy as np

# Points on each light's disc when its radius is positive: the cost is this many shadow rays
# per light and pixel (measured by scripts/bench_render.py); 16 leaves a step of 1/16 in visibility.
SOFT_SHADOW_SAMPLES = 16
GOLDEN_ANGLE = np.pi * (3.0 - np.sqrt(5.0))


def disc_pattern(samples: int) -> np.ndarray:
    """(samples, 2) points in the unit disc: the centre for one sample, else a Vogel spiral
    (point j at radius sqrt((j + 1/2) / n), angle j times the golden angle)."""
    if samples < 1:
        raise ValueError(f"a light needs at least one shadow sample, got {samples}")
    if samples == 1:
        return np.zeros((1, 2), np.float32)
    j = np.arange(samples)
    radius = np.sqrt((j + 0.5) / samples)
    angle = j * GOLDEN_ANGLE
    return np.stack([radius * np.cos(angle), radius * np.sin(angle)], axis=1).astype(np.float32)


def samples_for(light_radius: float, samples: int | None = None) -> int:
    """Shadow samples per light: ``samples`` when given, else one for point lights and
    :data:`SOFT_SHADOW_SAMPLES` for lights with a radius."""
    if samples is not None:
        if int(samples) < 1:
            raise ValueError(f"shadow samples must be >= 1, got {samples}")
        return int(samples)
    return 1 if float(light_radius) <= 0 else SOFT_SHADOW_SAMPLES
