"""The log joint of one test image in the 15-D unconstrained space.

    log p(z | I) = log p(z) + log p(I | render(f(z)))        (up to a constant)

log p(z) is the prior pushed back through the bijectors (with log-Jacobians,
:class:`mitsuba_p3.fit.priors.Prior`); f maps z to the renderer contract. The
render comes from Mitsuba through ``jax.pure_callback`` (one batched launch per
step of all chains) or, with ``renderer="jax"``, from the pure-JAX tracer
(:mod:`mitsuba_p3.infer.render_functions`).
"""
from __future__ import annotations

import functools
import numpy as np

from ..fit.fields import COLOURED
from ..fit.model import FittedModel
from ..fit.priors import Prior
from ..render import RENDERERS
from ..space import DIMENSION, HYPOTHESES, SLICES, render_params
from .chunks import map_in_chunks
from .likelihood import LikelihoodConfig, observe, score
from .material_moves import MaterialMoves
from .mcmc import Target
from .render_functions import jax_render_function, mitsuba_render_function
from .window import OUTSIDE_WINDOW, pixel_of, window_for, window_log_term


def contract_params(prior: Prior, z) -> dict:
    """z (..., 15) -> the renderer contract's object parameters (JAX): argmax class, clipped materials."""
    import jax.numpy as jnp

    return render_params(prior.constrain(z), xp=jnp)


class PosteriorCore(MaterialMoves):
    """Prior, renderer and likelihood of one fitted model at one image size: the whole
    posterior except the observed image, which every method takes as ``observation``
    (a pytree from :func:`mitsuba_p3.infer.likelihood.observe`). The material's moves come from
    :class:`~mitsuba_p3.infer.material_moves.MaterialMoves`.

    Because the image is an argument rather than a constant, one core -- and the
    sampler compiled for it -- serves every image of a data set: :meth:`shared`
    returns the cached core, so the Mitsuba scene load and the JIT compilation
    (several seconds) are paid once per process rather than once per image.
    """

    _cache: dict = {}

    def __init__(self, fitted: FittedModel, likelihood: LikelihoodConfig, renderer: str, height: int, width: int):
        from ..errors import MitsubaP3Error
        from ..render import make_renderer

        if renderer not in RENDERERS:
            raise MitsubaP3Error(f"unknown renderer {renderer!r}; choose mitsuba or jax")
        self.fitted = fitted
        self.prior = fitted.prior
        self.config = likelihood
        self.renderer_kind = renderer
        self.renderer = make_renderer(fitted.scene(), renderer, height=height, width=width,
                                      shadows=likelihood.shadows)
        self.channels = fitted.channels if likelihood.kind == "np3" else None
        # the empty floor, once per core: the likelihood's object/floor regions and the SMC's
        # footprint (pixels that differ from it by more than the fitted threshold) need it
        self.empty = self.renderer.render_empty()
        self.footprint_threshold = fitted.noise.footprint if (fitted.root / "noise.json").exists() else None
        self.spectra = fitted.noise_spectra if likelihood.spectral else None
        self._scored = {}         # (window size or None, bases) -> render function (see :meth:`_image`)
        # the shading fields' regions need the pixels each render's object covers: Mitsuba returns them
        # with the render itself; the JAX tracer's path traces them apart (:meth:`objects`)
        self._objects_rendered = likelihood.fields is not None and renderer == "mitsuba"
        # the whole image's render (:meth:`render`); the samplers' come from :meth:`_image`
        self._render = (mitsuba_render_function if renderer == "mitsuba" else jax_render_function)(self.renderer)

    @classmethod
    def shared(cls, fitted: FittedModel, likelihood: LikelihoodConfig, renderer: str, height: int,
               width: int) -> "PosteriorCore":
        """The process's core for this model (folder and contents), likelihood, renderer and size."""
        import json

        key = (str(fitted.root.resolve()), json.dumps(fitted.info, sort_keys=True), likelihood, renderer,
               height, width)
        if key not in cls._cache:
            cls._cache[key] = cls(fitted, likelihood, renderer, height, width)
        return cls._cache[key]

    def observe(self, observed: np.ndarray, window: tuple[int, int, int, int] | None = None,
                outside: float = OUTSIDE_WINDOW) -> dict:
        """The observation pytree of an image at this core's size; with ``window`` (top, left, height,
        width) only that window of it is scored (its ``window`` entry is the offset the renders take),
        and a scene whose object's centre lies outside it has log likelihood ``outside`` (its
        ``outside_window`` entry; :mod:`mitsuba_p3.infer.window`; 0 scores such a scene by the window alone)."""
        if window is None:
            return observe(observed, self.config, self.channels, self.empty, self.spectra)
        top, left, height, width = window
        crop = lambda image: np.asarray(image)[top:top + height, left:left + width]  # noqa: E731
        observation = observe(crop(observed), self.config, self.channels, crop(self.empty), self.spectra)
        observation["window"] = np.array([top, left], np.int32)
        observation["outside_window"] = np.float32(outside)
        return observation

    def window_for(self, observed: np.ndarray, size: tuple[int, int], margin: int = 8):
        """Where to score an image when only a ``size`` window is (:func:`~mitsuba_p3.infer.window.window_for`)."""
        return window_for(self, observed, size, margin)

    @functools.cached_property
    def camera(self):
        """The fitted scene's camera."""
        return self.fitted.scene().camera

    def pixel_of(self, points):
        """(..., 2) the (row, column) of this core's image in which 3-D points (..., 3) appear
        (:func:`~mitsuba_p3.infer.window.pixel_of`)."""
        return pixel_of(self.camera, self.renderer.height, self.renderer.width, points)

    def window_log_term(self, z, observation):
        """0, or the observation's ``outside_window`` where z's object lies outside its scoring window
        (:func:`~mitsuba_p3.infer.window.window_log_term`)."""
        return window_log_term(self, z, observation)

    def _scored_rays(self, observation):
        """(origin (3,), rays (h * w, 3)) of the pixels the observation scores: its window, or the whole image."""
        import jax
        import jax.numpy as jnp

        height, width = np.shape(observation["image"])[:2]
        origin, rays = self.camera_rays
        rays = jnp.asarray(rays).reshape(self.renderer.height, self.renderer.width, 3)
        if "window" in observation:
            top, left = observation["window"][0], observation["window"][1]
            rays = jax.lax.dynamic_slice(rays, (top, left, 0), (height, width, 3))
        return jnp.asarray(origin), rays.reshape(-1, 3)

    def objects(self, z, observation):
        """(h, w) the pixels of the scored image (the observation's window, or the whole image) that z's
        object covers, traced from its pose without shading (JAX; vmap for many); None unless the
        likelihood needs them (the shading fields' form). The samplers take Mitsuba's from its render
        (:meth:`_image`); this serves the JAX tracer's path and SBC's simulations."""
        if self.config.fields is None:
            return None
        from ..render.jax_tracer import silhouette

        covered = silhouette(self.params(z), *self._scored_rays(observation), self.renderer.floor_half_size)
        return covered.reshape(np.shape(observation["image"])[:2])

    def normals(self, z, observation):
        """(h, w, 3) z's object's world normals over the scored image ((0, 0, 1) off the object), traced from its
        pose (JAX); None unless the likelihood's fields live on the object's normals."""
        if self.config.fields is None or self.config.fields_object != "normals":
            return None
        from ..render.jax_tracer import surface_normals

        normal = surface_normals(self.params(z), *self._scored_rays(observation), self.renderer.floor_half_size)
        return normal.reshape(np.shape(observation["image"])[:2] + (3,))

    def _score(self, image, objects, observation, z):
        """The score of one render (h, w, 3) of position z whose object covers ``objects`` (h, w; None
        unless the likelihood needs them) (:func:`~mitsuba_p3.infer.likelihood.score`; tinted shading
        fields read z's colour)."""
        colours = self.params(z)["colour"][None] if self.config.fields_channels in COLOURED else None
        normals = self.normals(z, observation)
        return score(observation, image[None], self.config, self.channels,
                     None if objects is None else objects[None], colours,
                     None if normals is None else normals[None])[0]

    def _image(self, z, observation, bases: bool = False):
        """The render (or material bases) of z that ``observation`` scores -- its window, or the whole
        image -- and the pixels of it that z's object covers (None unless the likelihood needs them)."""
        size = tuple(np.shape(observation["image"])[:2]) if "window" in observation else None
        key = (size, bases)
        if key not in self._scored:
            if self.renderer_kind == "mitsuba":
                self._scored[key] = mitsuba_render_function(self.renderer, bases, size, self._objects_rendered)
            else:
                self._scored[key] = jax_render_function(self.renderer, bases, size)
        params = self.params(z)
        out = self._scored[key](params, observation["window"]) if size else self._scored[key](params)
        return out if self._objects_rendered else (out, self.objects(z, observation))

    @functools.cached_property
    def camera_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's origin (3,) and per-pixel unit rays (H*W, 3) at this core's size (the SMC's
        footprint proposal follows them); computed on first use, once per core."""
        from ..render.jax_tracer import camera_rays

        return camera_rays(self.fitted.scene().camera, self.renderer.height, self.renderer.width)

    def params(self, z) -> dict:
        """The renderer contract's object parameters of position(s) z (:func:`contract_params`)."""
        return contract_params(self.prior, z)

    def render(self, z):
        """Image(s) of unconstrained position(s) z (JAX)."""
        return self._render(self.params(z))

    def log_likelihood(self, z, observation):
        """log p(I | z) of one position z (15,) (JAX; vmap for many): the image's score and the window's
        term (:meth:`window_log_term`)."""
        return self.image_log_likelihood(z, observation) + self.window_log_term(z, observation)

    def image_log_likelihood(self, z, observation):
        """The score of z's render alone, without the window's term (the empty floor's evidence needs it)."""
        return self._score(*self._image(z, observation), observation, z)

    def log_likelihoods(self, z, observation, parts: bool | str = False):
        """:meth:`log_likelihood` of many positions z (B, 15) -> (B,), or with ``parts`` the pair (the score
        with the observation's weight ``parts`` at 0, the whole): ``neural_weight`` (or True), NP3's bridge
        (:meth:`log_likelihood_parts`), or ``scale_weight``, the image's own noise scale's bridge
        (:mod:`mitsuba_p3.infer.smc`). The B renders in one batch (one callback), their scores in chunks
        that stay in the CPU's cache (:mod:`~mitsuba_p3.infer.chunks`)."""
        import jax

        image, objects = jax.vmap(lambda p: self._image(p, observation))(z)
        term = jax.vmap(lambda p: self.window_log_term(p, observation))(z)
        weight = "neural_weight" if parts is True else parts

        def one(image, objects, p):
            if parts:
                return (self._score(image, objects, {**observation, weight: 0.0}, p),
                        self._score(image, objects, observation, p))
            return self._score(image, objects, observation, p)

        scores = map_in_chunks(one, (image, objects, z), image.shape[-3] * image.shape[-2])
        return tuple(s + term for s in scores) if parts else scores + term

    def log_likelihood_parts(self, z, observation):
        """(colour, whole) log likelihood of one position z from one render (JAX; vmap for many): the
        colour term alone, and with the neural term at the observation's weight (NP3's bridge)."""
        (image, objects), term = self._image(z, observation), self.window_log_term(z, observation)
        return (self._score(image, objects, {**observation, "neural_weight": 0.0}, z) + term,
                self._score(image, objects, observation, z) + term)

    def logdensity(self, z, observation):
        """log p(z) + log p(I | z) of one position z (15,) (JAX; vmap for many)."""
        return self.prior.log_prob(z) + self.log_likelihood(z, observation)

    def target(self, material_gibbs: bool = True) -> Target:
        """The sampler's view of this posterior: log density, prior draws, the discrete hypothesis
        of a point as its mode, the symmetry move after every walk and, with ``material_gibbs``,
        the material update after every step (the walk then leaves the materials to it)."""
        mask = np.ones(DIMENSION, np.float32)
        if material_gibbs:
            for name in ("colour", "ambient", "diffuse", "specular"):
                mask[SLICES[name]] = 0.0
        return Target(self.logdensity, self.prior.sample, self.prior.hypothesis, len(HYPOTHESES),
                      walk_move=self.symmetry_move, step_move=self.material_move if material_gibbs else None,
                      walk_mask=tuple(mask.tolist()))

    def symmetry_turn(self, key, position):
        """The symmetry move's proposal: ``position`` turned by 90, 180 or -90 degrees (each a third;
        90 swaps the x and y half-extents), and log |det dz'/dz| (the yaw's logistic coordinate is
        stretched by the turn). A turn's inverse is proposed as often as the turn, so the proposal is
        symmetric up to that Jacobian. Returns (turned position, log Jacobian)."""
        import jax
        import jax.numpy as jnp

        from .symmetry import quarter_turn

        return quarter_turn(position, jnp.array([1, 2, -1])[jax.random.randint(key, (), 0, 3)], jnp)

    def symmetry_move(self, key, state):
        """An MH move over the primitives' symmetries that does not render.

        Turn the object by 90 degrees (swapping its x and y half-extents), or by 180
        degrees (:meth:`symmetry_turn`). Every primitive (box, ellipsoid, elliptic
        cylinder) is the same shape after it, so the likelihood is taken as unchanged and
        the move is accepted with the MH ratio of the yaw prior. That holds only up to the
        renderer's rasterisation: a row of outline pixels can flip, and the likelihood then
        changes by tens of nats where the noise is small. The SMC's default therefore
        renders the turn and accepts it with its likelihood
        (:func:`mitsuba_p3.infer.smc_moves.kernels`, ``symmetry="rendered"``); this move serves
        the MH sampler. Without either, chains stay in one of the four equivalent yaw modes and
        R-hat never settles."""
        import jax
        import jax.numpy as jnp

        t = SLICES["theta"].start
        k_choice, k_accept = jax.random.split(key)
        z = state.position
        new, _ = self.symmetry_turn(k_choice, z)
        theta = -jnp.pi + 2 * jnp.pi * jax.nn.sigmoid(z[t])
        turned = -jnp.pi + 2 * jnp.pi * jax.nn.sigmoid(new[t])
        # log pi(z') - log pi(z) + log|det dz'/dz| reduces to the yaw prior's ratio
        log_ratio = self.prior.config.theta_concentration * (jnp.cos(turned) - jnp.cos(theta))
        accept = jnp.log(jax.random.uniform(k_accept)) < log_ratio
        # the log joint changes only through the prior's yaw term (likelihood and scale prior are invariant)
        new_logdensity = state.logdensity + self.prior.log_prob(new) - self.prior.log_prob(z)
        return type(state)(jnp.where(accept, new, z), jnp.where(accept, new_logdensity, state.logdensity))


class PosteriorModel:
    """The posterior of one observed image: a shared :class:`PosteriorCore` and the image's
    observation, with the core's methods bound to it."""

    def __init__(self, fitted: FittedModel, observed: np.ndarray, likelihood: LikelihoodConfig | None = None,
                 renderer: str = "mitsuba"):
        observed = np.asarray(observed, np.float32)
        self.core = PosteriorCore.shared(fitted, likelihood or LikelihoodConfig(), renderer, *observed.shape[:2])
        self.observation = self.core.observe(observed)
        self.prior, self.renderer = self.core.prior, self.core.renderer

    def render(self, z):
        return self.core.render(z)

    def log_likelihood(self, z):
        return self.core.log_likelihood(z, self.observation)

    def logdensity(self, z):
        return self.core.logdensity(z, self.observation)

    def material_move(self, key, state):
        return self.core.material_move(key, state, self.observation)
