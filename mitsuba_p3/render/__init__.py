"""Renderers behind one contract (:mod:`.contract`): Mitsuba, and the JAX tracer that cross-checks it.

Import a renderer through :func:`make_renderer`; this keeps Mitsuba's import
(which must follow the backend's libLLVM choice) out of module import time.
"""
from __future__ import annotations

RENDERERS = ("mitsuba", "jax")


def make_renderer(scene, kind: str = "mitsuba", height: int | None = None, width: int | None = None,
                  shadows: bool | None = None, shadow_samples: int | None = None):
    """A renderer of ``kind`` for ``scene`` at the given resolution (default: the camera's);
    ``shadow_samples`` points per light's disc (default: one for point lights, else
    :data:`~mitsuba_p3.render.soft_shadows.SOFT_SHADOW_SAMPLES`)."""
    from ..errors import SceneError

    if kind == "mitsuba":
        from .mitsuba import MitsubaRenderer

        return MitsubaRenderer(scene, height=height, width=width, shadows=shadows, shadow_samples=shadow_samples)
    if kind == "jax":
        from .jax_tracer import JaxRenderer

        return JaxRenderer(scene, height=height, width=width, shadows=shadows, shadow_samples=shadow_samples)
    raise SceneError(f"unknown renderer {kind!r}; choose one of {', '.join(RENDERERS)}")
