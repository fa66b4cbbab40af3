"""The scoring window: where an image is scored, and what scoring only there assumes.

Most of an image is empty floor that every scene explains alike, and renders cost in
proportion to their pixels, so the SMC scores only a window around the object
(``SMCConfig.window``): centred on the largest connected part of the image's footprint,
the pixels that differ from the fitted empty floor (:mod:`mitsuba_p3.infer.footprint`).

Scoring the window alone leaves out every pixel outside it. That is right while the
object is in the window: outside, every scene then renders the same floor. A scene whose
object lies elsewhere breaks it: in the whole image it would render the object on floor
the image shows bare, at a cost of hundreds of nats, while the window alone scores it as
the bare floor, better than any scene a few millimetres off the object. Runs of the SMC
settled on such scenes (all their likelihoods equal, so the tempering read them as a
posterior already found and went straight to lambda = 1), far below the truth. So the window's
assumption is part of the likelihood: a scene whose object's centre appears outside the
window has likelihood zero (:func:`window_log_term`). The centre (x, y, s_z) of a convex
object appears inside its own silhouette, so a window that holds the footprint holds the
truth; an object that straddles the window's edge keeps its window score.
"""
from __future__ import annotations

import numpy as np

# The log likelihood of a scene whose object's centre lies outside the scoring window: a probability of
# zero, written as the finite number the tempering kernel reads every non-finite log likelihood as, so
# lambda x it is never NaN (0 x -inf is)
OUTSIDE_WINDOW = -1e30


def window_for(core, observed: np.ndarray, size: tuple[int, int], margin: int = 8):
    """Where ``core`` scores an image when only a ``size`` window is: (top, left, height, width), centred
    on the largest connected part of its footprint (object and shadow). None (score the whole image)
    without a fitted footprint threshold, with an empty footprint, or when that part with ``margin``
    pixels around it does not fit the window."""
    from scipy import ndimage

    from .footprint import footprint_mask

    height, width = min(size[0], core.renderer.height), min(size[1], core.renderer.width)
    if core.footprint_threshold is None or (height, width) == (core.renderer.height, core.renderer.width):
        return None
    labels, count = ndimage.label(footprint_mask(observed, core.empty, core.footprint_threshold))
    if count == 0:
        return None
    largest = 1 + int(np.argmax(ndimage.sum(labels > 0, labels, range(1, count + 1))))
    rows, cols = np.nonzero(labels == largest)
    if np.ptp(rows) + 1 + 2 * margin > height or np.ptp(cols) + 1 + 2 * margin > width:
        return None
    top = int(np.clip((rows.min() + rows.max() + 1 - height) // 2, 0, core.renderer.height - height))
    left = int(np.clip((cols.min() + cols.max() + 1 - width) // 2, 0, core.renderer.width - width))
    return top, left, height, width


def pixel_of(camera, height: int, width: int, points):
    """(..., 2) the (row, column) of a ``height`` x ``width`` image of ``camera`` in which 3-D points
    (..., 3) appear, in pixel units with pixel (i, j)'s centre at (i, j) (JAX; the inverse of the
    camera's rays)."""
    import jax.numpy as jnp

    from ..render.jax_tracer import camera_frame

    origin, forward, left, up, tan_x, tan_y = (jnp.asarray(v, jnp.float32)
                                               for v in camera_frame(camera, height, width))
    d = points - origin
    depth = d @ forward
    column = (1.0 - (d @ left) / (depth * tan_x)) / 2 * width - 0.5
    row = (1.0 - (d @ up) / (depth * tan_y)) / 2 * height - 0.5
    return jnp.stack([row, column], axis=-1)


def window_log_term(core, z, observation):
    """0 where the object's centre (x, y, s_z) of position z appears inside ``observation``'s window,
    its ``outside_window`` entry (:data:`OUTSIDE_WINDOW` unless told otherwise) where it does not; 0 for
    an observation of the whole image (JAX)."""
    import jax.numpy as jnp

    if "window" not in observation:
        return jnp.float32(0.0)
    p = core.prior.constrain(z)
    centre = jnp.concatenate([p["shift"], p["scale"][..., 2:3]], axis=-1)
    pixel = pixel_of(core.camera, core.renderer.height, core.renderer.width, centre)
    start = jnp.asarray(observation["window"], jnp.float32) - 0.5
    size = jnp.asarray(np.shape(observation["image"])[:2], jnp.float32)
    inside = jnp.all((pixel >= start) & (pixel < start + size), axis=-1)
    return jnp.where(inside, 0.0, observation["outside_window"]).astype(jnp.float32)
