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

import functools
from typing import Callable, NamedTuple

import numpy as np

from .. import small_linalg
from ..fit.model import FittedModel
from ..fit.priors import Prior
from ..render import RENDERERS
from ..render.contract import OBJECT_SHAPES
from ..space import DIMENSION, HYPOTHESES, OBJECT_KEYS, SLICES, render_params
from .likelihood import LikelihoodConfig, fields_form, fields_masks, fields_regions, observe, score, whiten
from .mcmc import Target
from .window import OUTSIDE_WINDOW, pixel_of, window_for, window_log_term

# The ridge move's step: log s ~ N(0, RIDGE_STEP^2), a fifth of an e-fold of the colour's brightness.
RIDGE_STEP = 0.2


class MixtureConditional(NamedTuple):
    """A material conditional that is a mixture of trivariate Gaussians (component log weights (C,), means
    (C, 3), precisions and their Cholesky factors (C, 3, 3), log determinants (C,)), in natural units: the
    weights' (k_a, k_d, k_s) given the colour, the pose, the class and the shininess; the colour's given
    the weights where the noise couples the channels."""
    log_mix: object
    mean: object
    precision: object
    chol: object
    log_det_p: object

    @classmethod
    def of(cls, log_w, mu, var, lam, eta) -> "MixtureConditional":
        """The conditional of x under a prior mixture of diagonal Gaussians (log weights (C,), means and
        variances (C, 3)) times a Gaussian likelihood exp(-x'lam x / 2 + eta'x) (lam (3, 3), eta (3,)):
        each component's posterior, and its weight by the component's evidence."""
        import jax
        import jax.numpy as jnp

        precision = jax.vmap(jnp.diag)(1.0 / var) + lam                             # (C, 3, 3)
        h = mu / var + eta
        factor = small_linalg.cholesky(precision, jnp)       # written out: no LAPACK call (small_linalg)
        chol = small_linalg.as_matrix(factor, jnp)
        mean = small_linalg.solve(factor, h, jnp)
        log_det_p = small_linalg.log_det(factor, jnp)
        log_evidence = (-0.5 * jnp.sum(jnp.log(var), axis=1) - 0.5 * log_det_p + 0.5 * jnp.sum(h * mean, axis=1)
                        - 0.5 * jnp.sum(mu * mu / var, axis=1))
        return cls(jax.nn.log_softmax(log_w + log_evidence), mean, precision, chol, log_det_p)

    def log_q(self, w):
        import jax
        import jax.numpy as jnp

        d = w - self.mean                                                           # (C, 3)
        quad = jnp.einsum("ci,cij,cj->c", d, self.precision, d)
        return jax.scipy.special.logsumexp(self.log_mix + 0.5 * self.log_det_p - 1.5 * jnp.log(2 * jnp.pi)
                                           - 0.5 * quad)

    def draw(self, key):
        import jax
        import jax.numpy as jnp

        k_combo, k_noise = jax.random.split(key)
        combo = jax.random.categorical(k_combo, self.log_mix)
        noise = jax.random.normal(k_noise, (3,))
        factor = [[self.chol[combo][i, j] for j in range(3)] for i in range(3)]
        return self.mean[combo] + small_linalg.backward(factor, noise, jnp)


def contract_params(prior: Prior, z) -> dict:
    """z (..., 15) -> the renderer contract's object parameters (JAX): argmax class, clipped materials."""
    import jax.numpy as jnp

    return render_params(prior.constrain(z), xp=jnp)


def mitsuba_render_function(renderer, bases: bool = False, window: tuple[int, int] | None = None) -> Callable:
    """A JAX function params -> image(s) that renders with Mitsuba on the host.

    Works on one parameter set (image (H, W, 3)) and under ``jax.vmap`` (the
    callback then gets all sets at once and renders them in one launch). With
    ``bases`` it returns the material bases (H, W, 4, 3) of ``renderer.render_bases``.
    With ``window`` (height, width) the function is ``render(params, offset)``: only the
    window of the image whose top-left pixel is ``offset`` (2,) (:meth:`MitsubaRenderer.window`).
    """
    import jax
    import jax.numpy as jnp

    height, width = window or (renderer.height, renderer.width)
    pixel = (4, 3) if bases else (3,)
    views = {}

    def host(*arrays):
        if window:
            # the offset is the same for the whole batch (it belongs to the observation)
            top, left = (int(v) for v in np.asarray(arrays[-1]).reshape(-1, 2)[0])
            arrays = arrays[:-1]
            if (top, left) not in views:
                views.clear()
                views[top, left] = renderer.window(top, left, height, width)
            view = views[top, left]
        else:
            view = renderer
        # Under vmap an argument that is not batched arrives with size-1 leading axes:
        # broadcast every argument to the common batch shape, then flatten it.
        leading = [np.shape(a)[:np.ndim(a) - len(OBJECT_SHAPES[k])] for k, a in zip(OBJECT_KEYS, arrays)]
        batch_shape = np.broadcast_shapes(*leading)
        count = int(np.prod(batch_shape, dtype=np.int64))
        params = {key: np.broadcast_to(a, batch_shape + OBJECT_SHAPES[key]).reshape((count,) + OBJECT_SHAPES[key])
                  for key, a in zip(OBJECT_KEYS, arrays)}
        images = view.render_bases(params) if bases else view.render(params)
        return np.asarray(images, np.float32).reshape(batch_shape + (height, width) + pixel)

    def render(params: dict, offset=None):
        batch_shape = jnp.shape(params["theta"])
        out = jax.ShapeDtypeStruct(batch_shape + (height, width) + pixel, jnp.float32)
        extra = [jnp.asarray(offset, jnp.int32)] if window else []
        return jax.pure_callback(host, out, *[params[k] for k in OBJECT_KEYS], *extra, vmap_method="expand_dims")

    return render


def jax_render_function(renderer, bases: bool = False, window: tuple[int, int] | None = None) -> Callable:
    """A JAX function params -> image(s) (or bases) that renders with the JAX tracer: no callback,
    the whole likelihood stays a JAX program (on a GPU, on the device).

    Under ``jax.vmap`` a traced shape class would turn the tracer's ``lax.switch``
    over classes into a select that renders every class for every chain; the custom
    vmap rule instead hands the whole batch to the tracer's batched render, which
    renders it as the device prefers (:func:`~mitsuba_p3.render.jax_tracer.batching_for`).
    With ``window`` (height, width) the function is ``render(params, offset)``, as
    :func:`mitsuba_render_function`'s.
    """
    import jax
    import jax.numpy as jnp

    # numpy, not JAX arrays: this may be built while a sampler is being traced (a window's function is
    # made on first use), and a JAX array made then would be that trace's tracer, leaking into the next
    shared = {k: np.asarray(v) for k, v in renderer.params.items() if k not in OBJECT_KEYS}

    def draw(params: dict, offset):
        constants = {k: jnp.asarray(v) for k, v in shared.items()}     # made in the trace that uses them
        return renderer.render_jax({**constants, **params}, bases=bases, window=(offset, window) if window else None)

    render = jax.custom_batching.custom_vmap(draw)

    @render.def_vmap
    def render_batch(axis_size, in_batched, params, offset):
        flags = in_batched[0]
        params = {k: v if flags[k] else jnp.broadcast_to(v, (axis_size,) + jnp.shape(v)) for k, v in params.items()}
        if in_batched[1]:        # the offset belongs to the observation: the same for the whole batch
            offset = offset[0]
        return draw(params, offset), True

    if window:
        return lambda params, offset: render(params, jnp.asarray(offset, jnp.int32))
    return lambda params: render(params, jnp.zeros(2, jnp.int32))


class PosteriorCore:
    """Prior, renderer and likelihood of one fitted model at one image size: the whole
    posterior except the observed image, which every method takes as ``observation``
    (a pytree from :func:`mitsuba_p3.infer.likelihood.observe`).

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
        self._windowed = {}       # (window size, bases) -> render function (see :meth:`_image`)
        if renderer == "mitsuba":
            self._render = mitsuba_render_function(self.renderer)
            self._bases = mitsuba_render_function(self.renderer, bases=True)
        else:
            self._render = jax_render_function(self.renderer)
            self._bases = jax_render_function(self.renderer, bases=True)

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

    def objects(self, z, observation):
        """(h, w) the pixels of the scored image (the observation's window, or the whole image) that z's
        object covers, traced from its pose without shading (JAX; vmap for many); None unless the
        likelihood needs them (the shading fields' form)."""
        if self.config.fields is None:
            return None
        import jax
        import jax.numpy as jnp

        from ..render.jax_tracer import silhouette

        height, width = np.shape(observation["image"])[:2]
        origin, rays = self.camera_rays
        rays = jnp.asarray(rays).reshape(self.renderer.height, self.renderer.width, 3)
        if "window" in observation:
            top, left = observation["window"][0], observation["window"][1]
            rays = jax.lax.dynamic_slice(rays, (top, left, 0), (height, width, 3))
        params = contract_params(self.prior, z)
        covered = silhouette(params, jnp.asarray(origin), rays.reshape(-1, 3), self.renderer.floor_half_size)
        return covered.reshape(height, width)

    def _score(self, z, image, observation):
        """The score of one render of z (h, w, 3) (:func:`~mitsuba_p3.infer.likelihood.score`)."""
        objects = self.objects(z, observation)
        return score(observation, image[None], self.config, self.channels,
                     None if objects is None else objects[None])[0]

    def _image(self, z, observation, bases: bool = False):
        """The render (or material bases) of z that ``observation`` scores: its window, or the whole image."""
        params = contract_params(self.prior, z)
        if "window" not in observation:
            return (self._bases if bases else self._render)(params)
        size = tuple(np.shape(observation["image"])[:2])
        key = (size, bases)
        if key not in self._windowed:
            make = mitsuba_render_function if self.renderer_kind == "mitsuba" else jax_render_function
            self._windowed[key] = make(self.renderer, bases, size)
        return self._windowed[key](params, observation["window"])

    @functools.cached_property
    def camera_rays(self) -> tuple[np.ndarray, np.ndarray]:
        """The camera's origin (3,) and per-pixel unit rays (H*W, 3) at this core's size (the SMC's
        footprint proposal follows them); computed on first use, once per core."""
        from ..render.jax_tracer import camera_rays

        return camera_rays(self.fitted.scene().camera, self.renderer.height, self.renderer.width)

    def render(self, z):
        """Image(s) of unconstrained position(s) z (JAX)."""
        return self._render(contract_params(self.prior, z))

    def log_likelihood(self, z, observation):
        """log p(I | z) of one position z (15,) (JAX; vmap for many): the image's score and the window's
        term (:meth:`window_log_term`)."""
        return self.image_log_likelihood(z, observation) + self.window_log_term(z, observation)

    def image_log_likelihood(self, z, observation):
        """The score of z's render alone, without the window's term (the empty floor's evidence needs it)."""
        return self._score(z, self._image(z, observation), observation)

    def log_likelihood_parts(self, z, observation):
        """(colour, whole) log likelihood of one position z from one render (JAX; vmap for many): the
        colour term alone, and with the neural term at the observation's weight (NP3's bridge)."""
        image, term = self._image(z, observation), self.window_log_term(z, observation)
        return (self._score(z, image, {**observation, "neural_weight": 0.0}) + term,
                self._score(z, image, observation) + term)

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

    def ridge_move(self, key, state, log_prior=None, step: float = RIDGE_STEP):
        """An MH move along the colour/weight ridge; no render.

        The image sees the colour c only through the products c k_a and c k_d (the
        specular lobe is white), so the scene (c s, k_a / s, k_d / s) renders exactly
        like (c, k_a, k_d) for any s > 0, as long as no channel of c is clipped at 1.
        Along that ridge the posterior is the prior's, and the material update, which
        draws the colour given the weights and then the weights given the colour, crawls
        along it in tiny steps once the likelihood is sharp (each conditional is narrow):
        runs with different seeds then sit at different points of the same ridge. This
        move proposes log s ~ N(0, ``step``^2) and accepts with the prior ratio times the
        Jacobian s (c scales 3 coordinates by s, k_a and k_d two by 1/s; the affine maps to
        z cancel); a proposal or state with a channel of c above 1 is rejected (there the
        render would change), which keeps detailed balance. ``state.logdensity`` changes by
        the prior's difference only; ``log_prior`` defaults to :meth:`Prior.log_prob`."""
        import jax
        import jax.numpy as jnp

        log_prior = log_prior or self.prior.log_prob
        k_step, k_accept = jax.random.split(key)
        z = state.position
        x = self.prior.constrain(z)
        log_s = step * jax.random.normal(k_step)
        s = jnp.exp(log_s)
        new = z
        for name, factor in (("colour", s), ("ambient", 1.0 / s), ("diffuse", 1.0 / s)):
            g = self.prior.gmms[name]
            value = x[name] if name == "colour" else x[name][..., None]
            new = new.at[SLICES[name]].set((value * factor - g.mean) / g.std)
        new_colour = x["colour"] * s
        inside = (jnp.max(x["colour"]) <= 1.0) & (jnp.max(new_colour) <= 1.0)
        delta = log_prior(new) - log_prior(z)
        accept = inside & (jnp.log(jax.random.uniform(k_accept)) < delta + log_s)
        return type(state)(jnp.where(accept, new, z), jnp.where(accept, state.logdensity + delta, state.logdensity))

    def material_move(self, key, state, observation, tempering=1.0, log_prior=None):
        """Metropolis-within-Gibbs update of the materials of one chain's state: colour, then (k_a, k_d, k_s).

        One render of the material bases (:meth:`render_bases` of the renderers) makes
        the image an explicit function of the materials at the current pose, class and
        shininess: ``clip(c (k_a A + k_d D) + k_s S + F)``. Before clipping it is affine
        in the colour given the weights, and affine in the weights given the colour.
        With the Gaussian form of the colour likelihood and the GMM priors, each
        conditional is then a Gaussian mixture; a draw from it is an independence
        proposal, accepted by MH with the exact log joint, computed from the bases
        without another render (clipping, truncation and the neural term included).
        Returns (new state, both accepted).

        For a tempered target ``log_prior(z) + tempering * log p(I | z)`` (sequential Monte Carlo),
        pass ``tempering`` and the prior (default: :meth:`Prior.log_prob`); ``state.logdensity`` is
        then that target's value.
        """
        state, accepted, _, _ = self.scored_material_move(key, state, observation, tempering, log_prior)
        return state, accepted

    def scored_material_move(self, key, state, observation, tempering=1.0, log_prior=None, jump: bool = False):
        """:meth:`material_move`, also returning log p(I | z) of the new state, computed from the
        bases it rendered: a tempered sampler needs the likelihood apart from the prior, and this
        saves it a render per move. With ``jump``, the material kind's jump (:meth:`_kind_jump`, one
        more render) comes first. Returns (state, colour and weights accepted, log likelihood, jump
        accepted (False without ``jump``))."""
        import jax
        import jax.numpy as jnp

        k_colour, k_weights, k_jump = jax.random.split(key, 3)
        bases = self._image(state.position, observation, bases=True)
        gram = self._gram(bases, observation, tempering, state.position)
        # the material moves leave the pose, so the window's term (mitsuba_p3.infer.window) is the state's throughout
        term = self.window_log_term(state.position, observation)
        target = (tempering, log_prior or self.prior.log_prob, term)
        jumped = jnp.asarray(False)
        if jump:
            state, jumped, bases, gram = self._kind_jump(k_jump, state, bases, gram, observation, target)
        state, colour_ok = self._colour_move(k_colour, state, bases, gram, observation, target)
        state, weights_ok = self._weights_move(k_weights, state, bases, gram, observation, target)
        loglik = self._score(state.position, self._image_from_bases(bases, state.position), observation) + term
        return state, colour_ok & weights_ok, loglik, jumped

    def _gram(self, bases, observation, tempering, z):
        """The tempered precision-weighted inner products of the bases A, D, S and the residual
        r = I_obs - F, each taken in one colour channel: both material conditionals need only these.
        (3, 4, 4) per channel where the noise keeps the channels apart; (3, 3, 4, 4) [c, c', i, j]
        where it couples them (shading fields shared across channels, :mod:`mitsuba_p3.fit.fields`)."""
        import jax.numpy as jnp

        vectors = jnp.concatenate([bases[..., :3, :], (observation["image"] - bases[..., 3, :])[..., None, :]],
                                  axis=-2)                                          # (h, w, 4, 3)
        precision = tempering * self.config.power / self.config.sigma ** 2
        if self.config.spectral:
            # the spectral form's quadratic is that of whitened images (linear), at precision power
            vectors = jnp.moveaxis(whiten(jnp.moveaxis(vectors, -2, 0), observation, self.config), 0, -2)
            precision = tempering * self.config.power
        flat = vectors.reshape(-1, 12)                                              # (pixels, 4 x 3)
        full = (flat.T @ flat).reshape(4, 3, 4, 3)                                  # one matmul: XLA's fast path
        # the Gaussian part of the likelihood (outliers are left to the MH test)
        gram = jnp.einsum("icjc->cij", full)
        if self.config.fields is not None:
            correction = self._fields_correction(vectors, bases, observation, z)    # (3, 3, 4, 4)
            if self.config.fields_channels == "independent":
                gram = gram - jnp.einsum("ccij->cij", correction)
            else:
                gram = jnp.einsum("cd,cij->cdij", jnp.eye(3, dtype=gram.dtype), gram) - correction
        return gram * precision

    def _fields_correction(self, vectors, bases, observation, z):
        """(3, 3, 4, 4) [c, c', i, j] what the shading fields take off the inner products of vector i in
        channel c and vector j in channel c': under covariance sigma^2 I + B T B' the precision is
        (I - B (G + sigma^2 T^-1)^-1 B') / sigma^2, so x'Qy is the white x'y / sigma^2 less
        (B'x)' (G + sigma^2 T^-1)^-1 (B'y) / sigma^2 (:mod:`mitsuba_p3.fit.fields`). Zero for c != c' when
        every field is a single channel's. The regions are the pose's: its object's pixels, the floor
        its shadow changes, and the rest of the floor where the form has that region (the materials move
        none of them)."""
        import jax.numpy as jnp

        from ..fit.fields import column_statistics, field_statistics

        height, width = vectors.shape[:2]
        masks = fields_masks(bases[..., 3, :], self.objects(z, observation), observation["empty"],
                             fields_regions(self.config))
        variances, basis, loading = fields_form(self.config, height, width)
        statistics = field_statistics(jnp.moveaxis(vectors, -2, 0), masks, basis, xp=jnp)   # b: (4, R, k, 3)
        _, gram, _, _ = column_statistics(statistics, loading, xp=jnp)                       # (R, K, K)
        loading = jnp.asarray(loading, gram.dtype)
        # B'x for vector i taken in channel c alone: (4, 3, R, K)
        columns = jnp.einsum("jmc,irmc->icrj", loading, statistics[2])
        size = gram.shape[-1]
        inner = gram + (self.config.sigma ** 2 / jnp.asarray(variances, gram.dtype))[..., None] * jnp.eye(size)
        solved = small_linalg.solve(small_linalg.cholesky(inner, jnp), columns, jnp)        # (4, 3, R, K)
        return jnp.einsum("icrk,jdrk->cdij", columns, solved)

    def _kind_jump(self, key, state, bases, gram, observation, target):
        """The material kind's jump: a new shininess drawn from its prior (a mixture of the fitted
        materials' components: broad highlights and tight ones), the weights (k_a, k_d, k_s) drawn from
        their conditional at the new shininess's bases (one render) given the colour, accepted with the
        Hastings ratio of that independence proposal, whose reverse density takes the weights'
        conditional at the current bases. The walk moves the shininess only locally and the weights
        follow it only through the Gibbs update, so a run whose particles settled on one kind of
        highlight could keep them there; this move proposes the other kind whole (on fsclvr's misread
        metals it found no missed mode: docs/notebook.md). Returns (state, accepted, bases and gram of
        the state kept)."""
        import jax
        import jax.numpy as jnp

        k_component, k_noise, k_weights, k_accept = jax.random.split(key, 4)
        g = self.prior.gmms["shininess"]
        s = SLICES["shininess"].start
        loc, std = float(g.mean[0]), float(g.std[0])
        means, sds = jnp.asarray(g.means[:, 0]), jnp.sqrt(jnp.asarray(g.variances[:, 0]))
        component = jax.random.categorical(k_component, jnp.log(jnp.asarray(g.weights)))
        alpha = means[component] + sds[component] * jax.random.normal(k_noise)

        def log_q_alpha(z_alpha):    # the prior's density in the natural unit (its Jacobian std cancels)
            return g.log_prob((loc + std * z_alpha)[None])

        position = state.position
        moved = position.at[s].set((alpha - loc) / std)
        new_bases = self._image(moved, observation, bases=True)
        new_gram = self._gram(new_bases, observation, target[0], moved)
        colour = contract_params(self.prior, position)["colour"]
        dims, w_loc, w_std = self._weight_coordinates()
        old, new = self._weights_conditional(gram, colour), self._weights_conditional(new_gram, colour)
        weights = new.draw(k_weights)
        new_position = moved.at[dims].set((weights - w_loc) / w_std)
        log_q_ratio = (log_q_alpha(position[s]) + old.log_q(w_loc + w_std * position[dims])
                       - log_q_alpha(new_position[s]) - new.log_q(weights))
        state, accepted = self._independence_mh(k_accept, state, new_position, new_bases, log_q_ratio,
                                                observation, target)
        return (state, accepted, jnp.where(accepted, new_bases, bases), jnp.where(accepted, new_gram, gram))

    def _image_from_bases(self, bases, z):
        """The image at position z whose pose, class and shininess gave ``bases`` (H, W, 4, 3)."""
        import jax.numpy as jnp

        p = contract_params(self.prior, z)
        A, D, S, F = (bases[..., i, :] for i in range(4))
        return jnp.clip(p["colour"] * (p["ambient"] * A + p["diffuse"] * D) + p["specular"] * S + F, 0.0, 1.0)

    def _colour_move(self, key, state, bases, gram, observation, target):
        """The colour's conditional given the weights: a 3-D Gaussian mixture (one per GMM component)."""
        import jax
        import jax.numpy as jnp

        position = state.position
        gmm = self.prior.gmms["colour"]
        cols = slice(SLICES["colour"].start, SLICES["colour"].stop)
        p = contract_params(self.prior, position)
        # per channel, I = c * slope + offset with slope = k_a A + k_d D and offset = k_s S + F
        slope = jnp.stack([p["ambient"], p["diffuse"], 0.0 * p["specular"]])
        offset = jnp.stack([0.0, 0.0, p["specular"]])
        if gram.ndim == 4:
            return self._coupled_colour_move(key, state, bases, gram, observation, target, slope, offset)
        precision = jnp.einsum("i,cij,j->c", slope, gram[:, :3, :3], slope)       # sum slope^2 / sigma^2
        linear = slope @ gram[:, :3, 3].T - jnp.einsum("i,cij,j->c", slope, gram[:, :3, :3], offset)
        means, variances = jnp.asarray(gmm.means), jnp.asarray(gmm.variances)       # (K, 3)
        post_precision = 1.0 / variances + precision
        post_mean = (means / variances + linear) / post_precision
        log_evidence = jnp.sum(-0.5 * jnp.log1p(variances * precision)
                               + (variances * linear ** 2 + 2 * means * linear - precision * means ** 2)
                               / (2 * (1 + variances * precision)), axis=1)
        log_weights = jax.nn.log_softmax(jnp.log(jnp.asarray(gmm.weights)) + log_evidence)

        def log_q(c):
            per = -0.5 * (jnp.sum(post_precision * (c - post_mean) ** 2, axis=1)
                          - jnp.sum(jnp.log(post_precision / (2 * jnp.pi)), axis=1))
            return jax.scipy.special.logsumexp(log_weights + per)

        k_component, k_noise, k_accept = jax.random.split(key, 3)
        component = jax.random.categorical(k_component, log_weights)
        proposal = post_mean[component] + jax.random.normal(k_noise, (3,)) / jnp.sqrt(post_precision[component])
        current = jnp.asarray(gmm.mean) + jnp.asarray(gmm.std) * position[cols]
        new_position = position.at[cols].set((proposal - gmm.mean) / gmm.std)
        return self._independence_mh(k_accept, state, new_position, bases, log_q(current) - log_q(proposal),
                                     observation, target)

    def _coupled_colour_move(self, key, state, bases, gram, observation, target, slope, offset):
        """:meth:`_colour_move` where the noise couples the channels (``gram`` (3, 3, 4, 4)): each GMM
        component's conditional is then a full trivariate Gaussian (:meth:`_coupled_colour_conditional`)."""
        import jax
        import jax.numpy as jnp

        position = state.position
        gmm = self.prior.gmms["colour"]
        cols = slice(SLICES["colour"].start, SLICES["colour"].stop)
        conditional = self._coupled_colour_conditional(gram, slope, offset)
        k_draw, k_accept = jax.random.split(key)
        proposal = conditional.draw(k_draw)
        current = jnp.asarray(gmm.mean) + jnp.asarray(gmm.std) * position[cols]
        new_position = position.at[cols].set((proposal - gmm.mean) / gmm.std)
        return self._independence_mh(k_accept, state, new_position, bases,
                                     conditional.log_q(current) - conditional.log_q(proposal), observation, target)

    def _coupled_colour_conditional(self, gram, slope, offset):
        """The colour's conditional given the weights under coupled channels (``gram`` (3, 3, 4, 4)), the
        render I = c * slope + offset per channel: a :class:`MixtureConditional`, one full trivariate
        Gaussian per GMM component. Exact where the colour stays in [0, 1] (the renderer clips it; the MH
        test corrects the rest)."""
        import jax.numpy as jnp

        gmm = self.prior.gmms["colour"]
        quadratic = jnp.einsum("i,cdij,j->cd", slope, gram[:, :, :3, :3], slope)                # (3, 3)
        linear = (jnp.einsum("i,cdi->c", slope, gram[:, :, :3, 3])
                  - jnp.einsum("i,cdij,j->c", slope, gram[:, :, :3, :3], offset))
        return MixtureConditional.of(jnp.log(jnp.asarray(gmm.weights)), jnp.asarray(gmm.means),
                                     jnp.asarray(gmm.variances), quadratic + 1e-9 * jnp.eye(3), linear)

    def _weight_coordinates(self):
        """The weights (k_a, k_d, k_s): their coordinates in z and the affine map's loc and std (3,)."""
        import jax.numpy as jnp

        gmms = [self.prior.gmms[n] for n in ("ambient", "diffuse", "specular")]
        return (jnp.array([SLICES[n].start for n in ("ambient", "diffuse", "specular")]),
                jnp.array([g.mean[0] for g in gmms]), jnp.array([g.std[0] for g in gmms]))

    def _weights_conditional(self, gram, colour) -> "MixtureConditional":
        """The weights' conditional given the colour and the bases whose ``gram`` is given: a mixture of
        8 trivariate Gaussians (their priors are independent 2-component GMMs)."""
        import itertools

        import jax.numpy as jnp

        gmms = [self.prior.gmms[n] for n in ("ambient", "diffuse", "specular")]
        # every combination of one component per weight: weights (C,), means and variances (C, 3)
        combos = list(itertools.product(*[range(len(g.weights)) for g in gmms]))
        log_w = jnp.array([sum(np.log(g.weights[i]) for g, i in zip(gmms, c)) for c in combos])
        mu = jnp.array([[g.means[i, 0] for g, i in zip(gmms, c)] for c in combos])
        var = jnp.array([[g.variances[i, 0] for g, i in zip(gmms, c)] for c in combos])
        # per channel the image is w . (k_a A, k_d D, k_s S) + F with w = (c, c, 1)
        w = jnp.stack([colour, colour, jnp.ones(3)], axis=-1)                      # (3 channels, 3)
        if gram.ndim == 4:          # channels coupled by the noise: [c, c', i, j]
            lam = jnp.einsum("ci,cdij,dj->ij", w, gram[:, :, :3, :3], w) + 1e-9 * jnp.eye(3)
            eta = jnp.einsum("ci,cdi->i", w, gram[:, :, :3, 3])
        else:
            lam = jnp.einsum("ci,cij,cj->ij", w, gram[:, :3, :3], w) + 1e-9 * jnp.eye(3)
            eta = jnp.einsum("ci,ci->i", w, gram[:, :3, 3])
        return MixtureConditional.of(log_w, mu, var, lam, eta)

    def _weights_move(self, key, state, bases, gram, observation, target):
        """The weights' conditional given the colour (:meth:`_weights_conditional`): an independence
        proposal drawn from it, accepted with the exact log joint."""
        import jax

        k_draw, k_accept = jax.random.split(key)
        position = state.position
        dims, loc, std = self._weight_coordinates()
        conditional = self._weights_conditional(gram, contract_params(self.prior, position)["colour"])
        proposal = conditional.draw(k_draw)
        current = loc + std * position[dims]
        new_position = position.at[dims].set((proposal - loc) / std)
        return self._independence_mh(k_accept, state, new_position, bases,
                                     conditional.log_q(current) - conditional.log_q(proposal), observation, target)

    def _independence_mh(self, key, state, new_position, bases, log_q_ratio, observation, target):
        """Accept or reject an independence proposal with the exact (tempered) log joint, the image
        computed from the bases; ``target`` is (tempering, log prior, the window's term of the pose, which
        a material move keeps)."""
        import jax
        import jax.numpy as jnp

        tempering, log_prior, term = target
        image = self._image_from_bases(bases, new_position)
        new_logdensity = (log_prior(new_position)
                          + tempering * (self._score(new_position, image, observation) + term))
        accept = jnp.log(jax.random.uniform(key)) < new_logdensity - state.logdensity + log_q_ratio
        return (type(state)(jnp.where(accept, new_position, state.position),
                            jnp.where(accept, new_logdensity, state.logdensity)), accept)


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
