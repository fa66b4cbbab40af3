"""The log joint of one test image in the 15-D unconstrained space.

    log p(z | I) = log p(z) + log p(I | render(f(z)))        (up to a constant)

log p(z) is the prior pushed back through the bijectors (with log-Jacobians,
:class:`mitsuba_p3.fit.priors.Prior`); f maps z to the renderer contract. The
render comes from Mitsuba through ``jax.pure_callback`` -- under ``vmap`` over
chains the callback receives every chain's parameters at once
(``vmap_method="expand_dims"``), so one step of all chains is one batched
Mitsuba launch -- or, with ``renderer="jax"``, from the pure-JAX tracer.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..fit.model import FittedModel
from ..fit.priors import Prior, render_params
from .likelihood import ImageLikelihood, LikelihoodConfig

OBJECT_KEYS = ("shift", "theta", "scale", "kappa", "colour", "ambient", "diffuse", "specular", "shininess")
RENDERERS = ("mitsuba", "jax")


def contract_params(prior: Prior, z) -> dict:
    """z (..., 15) -> the renderer contract's object parameters (JAX): argmax class, clipped materials."""
    import jax.numpy as jnp

    return render_params(prior.constrain(z), xp=jnp)


def mitsuba_render_function(renderer) -> Callable:
    """A JAX function params -> image(s) that renders with Mitsuba on the host.

    Works on one parameter set (image (H, W, 3)) and under ``jax.vmap`` (the
    callback then gets all sets at once and renders them in one launch).
    """
    import jax
    import jax.numpy as jnp

    height, width = renderer.height, renderer.width

    def host(*arrays):
        batch_shape = np.shape(arrays[1])  # theta: one value per image
        count = int(np.prod(batch_shape, dtype=np.int64))
        params = {key: np.asarray(a).reshape((count,) + np.shape(a)[len(batch_shape):])
                  for key, a in zip(OBJECT_KEYS, arrays)}
        images = renderer.render(params)
        return np.asarray(images, np.float32).reshape(batch_shape + (height, width, 3))

    def render(params: dict):
        batch_shape = jnp.shape(params["theta"])
        out = jax.ShapeDtypeStruct(batch_shape + (height, width, 3), jnp.float32)
        return jax.pure_callback(host, out, *[params[k] for k in OBJECT_KEYS], vmap_method="expand_dims")

    return render


class PosteriorModel:
    """Prior, renderer and likelihood of one observed image; :meth:`logdensity` is the sampler's target."""

    def __init__(self, fitted: FittedModel, observed: np.ndarray, likelihood: LikelihoodConfig | None = None,
                 renderer: str = "mitsuba"):
        from ..errors import MitsubaP3Error
        from ..render import make_renderer

        if renderer not in RENDERERS:
            raise MitsubaP3Error(f"unknown renderer {renderer!r}; choose mitsuba or jax")
        self.fitted = fitted
        self.prior = fitted.prior
        self.config = likelihood or LikelihoodConfig()
        observed = np.asarray(observed, np.float32)
        height, width = observed.shape[:2]
        self.renderer_kind = renderer
        self.renderer = make_renderer(fitted.scene(), renderer, height=height, width=width, shadows=False)
        channels = fitted.channels if self.config.kind == "np3" else None
        self.likelihood = ImageLikelihood(observed, self.config, channels)
        if renderer == "mitsuba":
            self._render = mitsuba_render_function(self.renderer)
        else:
            import jax.numpy as jnp

            shared = {k: jnp.asarray(v) for k, v in self.renderer.params.items() if k not in OBJECT_KEYS}
            self._render = lambda params: self.renderer.render_jax({**shared, **params})

    def render(self, z):
        """Image(s) of unconstrained position(s) z (JAX)."""
        return self._render(contract_params(self.prior, z))

    def log_likelihood(self, z):
        """log p(I | z) of one position z (15,) (JAX; vmap for many)."""
        return self.likelihood(self.render(z)[None])[0]

    def logdensity(self, z):
        """log p(z) + log p(I | z) of one position z (15,) (JAX; vmap for many)."""
        return self.prior.log_prob(z) + self.log_likelihood(z)
