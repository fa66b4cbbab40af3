"""Inverse-square falloff of the point lights: an option beside the paper's lights, which have none.

A physical light of intensity I at distance d gives an irradiance I cos(theta) / d^2: floors grow darker away
from their lights. The paper's Phong lights do not fall off, so a fitted world can only make that gradient by
placing a light a hand's width above the object, where its direction sweeps across the floor; that light then
casts the object's shadow toward the camera, where no real shadow falls. With ``light_falloff`` = d0 > 0 every
light's intensity is scaled by (d0 / d)^2: an intensity is the light's at the reference distance d0, so fitted
intensities keep the scale of the paper's (d0 about the lights' distance from the table).

The one function below works on Dr.Jit and JAX arrays alike (plain arithmetic), so the Mitsuba integrator, the
batched Mitsuba renderer and the JAX tracer share it.
"""
from __future__ import annotations


def falloff(reference, distance):
    """(reference / distance)^2: the share of a light's intensity, given at ``reference`` metres, that reaches a
    point ``distance`` metres from it."""
    ratio = reference / distance
    return ratio * ratio
