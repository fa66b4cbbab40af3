"""Image likelihoods: the colour likelihood (P3) and the neural likelihood (NP3's extra term).

Colour: every pixel's residual r = I - render (3 channels) is scored by the
noise model of :mod:`mitsuba_p3.fit.noise`, an inlier truncated normal (scale
sigma) mixed with a uniform outlier (weight eps), and the sum over pixels is
raised to the power beta:

    log p = beta * sum over pixels of log[(1 - eps) prod_c TN(r_c; 0, sigma, [-1, 1]) + eps / 8]

With ``spectral`` (``--noise spectral``) the residual window is instead a stationary Gaussian
random field with the power spectrum P fitted on the train split's residual windows
(:mod:`mitsuba_p3.fit.noise`): the residual is whitened by 1 / sqrt(P) in the Fourier
domain and scored as white noise,

    log p = beta * (-1/2 ||whiten(r)||^2 - 1/2 sum_k log(2 pi P(k)))

so the low-frequency shading mismatch the Phong model always leaves is discounted and
the edges keep their weight (beta here is the small leftover correlation's power). A
stationary field also discounts a small object's whole appearance, so an object moved
out of the window can cost less than one a few millimetres off: not a default.

With ``fields`` (``--noise fields``) the mismatch is tied to what the hypothesis renders: smooth
shading fields on its own object's pixels, on the floor its shadow changes and (in forms fitted
with three regions) on the rest of the floor, integrated out (:mod:`mitsuba_p3.fit.fields`), so a
wrong shade or the image's own lighting costs little while the outline and the object's presence
keep their evidence; beta, the power of the correlation the fields leave, tempers the pixels given
the fields and not the fields' prior (a white scale sigma / sqrt(beta), power 1). This form
needs each render's object pixels, which :class:`~mitsuba_p3.infer.model.PosteriorCore` traces from
the pose (``objects`` of :func:`score`). ``--noise scaled`` is the same form with the image's own
noise scale integrated out under the prior the fit learnt from the train windows
(:mod:`mitsuba_p3.fit.fields`, "An image's own scale"): an image the model renders worse than its
train images has its evidence tempered by its own misfit.

With eps = 0 and beta = 1 the first form is the paper's likelihood, sigma = 1.0 (0.35 on its
dark set), a sum of truncated normals over every pixel and channel: the default
(``--noise paper``). ``--noise fitted`` uses the numbers the fit measured on the
train split's residuals: a Gaussian (eps = 0) with their RMS as sigma and the power
beta of their correlation; ``--noise robust`` the fitted mixture
(:func:`mitsuba_p3.infer.posterior.default_likelihood`).

Neural: -weight * sum over the selected VGG16 channels m of the pixel-mean of
(F_m(I) - F_m(render))^2, weight 0.05. Both are ``jax.numpy`` functions of a
batch of renders (B, H, W, 3), so they run inside the jitted sampler.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fit.features import Channel, neural_distance, selected_features

LIKELIHOODS = ("p3", "np3")
# fitted: the Gaussian noise fitted to the train residuals (sigma, power 1 / correlation area); sandwich:
# the same Gaussian at the composite likelihood's power along the pose; robust: the fitted inlier/outlier
# mixture; spectral: the correlated Gaussian field fitted to the train residual windows; fields: the shading
# fields on the hypothesis's own object, its shadow and the rest of the floor, marginalised
# (:mod:`mitsuba_p3.fit.fields`); scaled: the same fields with the image's noise scale integrated out
# (:mod:`mitsuba_p3.fit.fields`, "An image's own scale"); paper: sigma 1
# (:mod:`mitsuba_p3.fit.noise` says why fitted is Gaussian, and what each power is)
NOISES = ("fitted", "sandwich", "robust", "spectral", "fields", "scaled", "paper")
# the noise model infer, evaluate, reproduce and sbc use unless told otherwise, chosen on train classes: the shading
# fields with the floor's region decide the shape at least as often as the fitted Gaussian on every world
DEFAULT_NOISE = "fields"


@dataclass(frozen=True)
class LikelihoodConfig:
    """Which likelihood and its numbers (paper defaults)."""

    kind: str = "np3"             # p3: colour only; np3: colour + neural
    sigma: float = 1.0            # inlier scale per channel (the paper: 1.0; 0.35 on its dark set)
    outlier: float = 0.0          # eps, the outlier probability per pixel (the paper: 0)
    object_outlier: float | None = None   # eps where the render differs from the empty floor (None: eps)
    power: float = 1.0            # beta, the power of the colour likelihood (the paper: 1)
    shadows: bool = False         # hard shadows in the likelihood's renders (the paper: off)
    neural_weight: float = 0.05
    spectral: bool = False        # the correlated form: whiten by the fitted spectrum (sigma only reported)
    fields: tuple | None = None   # the shading fields' taus (region-major, degree 0..fields_degree); None: none
    fields_degree: int = 1
    fields_channels: str = "independent"   # how the fields load on r, g, b (mitsuba_p3.fit.fields.CHANNELS)
    # the image's noise scale, integrated out: (the inverse-gamma prior's shape and rate, the effective count
    # per value); None: the scale fixed at 1 (mitsuba_p3.fit.fields, "An image's own scale"; fields form only)
    scale: tuple | None = None
    # the object's field basis: "pixels" (the window's monomials) or "normals" (the spherical harmonics of the
    # hypothesis's surface normals, mitsuba_p3.fit.irradiance; the renders' normals are then needed)
    fields_object: str = "pixels"

    def __post_init__(self):
        from ..errors import ConfigError

        if self.kind not in LIKELIHOODS:
            raise ConfigError(f"unknown likelihood {self.kind!r}; choose p3 or np3")
        if not (isinstance(self.sigma, (int, float)) and np.isfinite(self.sigma) and self.sigma > 0):
            raise ConfigError(f"the colour likelihood's sigma must be a positive number; got {self.sigma}")
        if not (0.0 <= self.outlier < 1.0):
            raise ConfigError(f"the outlier probability must lie in [0, 1); got {self.outlier}")
        if self.object_outlier is not None and not (0.0 < self.object_outlier < 1.0 and self.outlier > 0.0):
            raise ConfigError(f"an object outlier probability needs both in (0, 1); got {self.object_outlier}, "
                              f"{self.outlier}")
        if not (np.isfinite(self.power) and 0.0 < self.power <= 1.0):
            raise ConfigError(f"the likelihood power must lie in (0, 1]; got {self.power}")
        if not (np.isfinite(self.neural_weight) and self.neural_weight >= 0):
            raise ConfigError(f"the neural weight must be >= 0; got {self.neural_weight}")
        if self.spectral and (self.outlier > 0 or self.object_outlier is not None):
            raise ConfigError("the spectral noise form has no outlier weights")
        if self.fields is not None:
            if self.spectral or self.outlier > 0 or self.object_outlier is not None:
                raise ConfigError("the shading fields' form has no outlier weights and no spectrum")
            from ..fit.fields import CHANNELS, region_count

            if self.fields_channels not in CHANNELS:
                raise ConfigError(f"the shading fields' channels must be one of {', '.join(CHANNELS)}; got "
                                  f"{self.fields_channels!r}")
            if self.fields_object not in ("pixels", "normals"):
                raise ConfigError(f"the shading fields' object basis is pixels or normals; got {self.fields_object!r}")
            try:
                if self.fields_object == "normals":
                    from ..fit.irradiance import normal_regions

                    normal_regions(self.fields)
                else:
                    region_count(self.fields, self.fields_degree, self.fields_channels)
            except ValueError as exc:
                raise ConfigError(str(exc)) from None
            if not all(np.isfinite(t) and t > 0 for t in self.fields):
                raise ConfigError(f"the shading fields' scales must be positive; got {self.fields}")
        if self.scale is not None:
            if self.fields is None:
                raise ConfigError("an image's own noise scale is integrated out under the shading fields' form only")
            if len(self.scale) != 3 or not all(np.isfinite(v) and v > 0 for v in self.scale) or self.scale[2] > 1:
                raise ConfigError(f"the noise scale needs a positive shape, rate and effective count per value "
                                  f"(at most 1); got {self.scale}")


def whiten(images, observation: dict, config: LikelihoodConfig):
    """Images (..., h, w, 3) as the likelihood's noise model sees them (JAX): filtered by 1 / sqrt(P)
    under the spectral form (``observation["spectrum"]``, (h, w // 2 + 1, 3)), divided by sigma
    otherwise. The Gaussian part of the colour likelihood is -1/2 beta ||whiten(r)||^2 + constant,
    and whitening is linear: the material update's Gram matrices are those of whitened bases."""
    import jax.numpy as jnp

    if not config.spectral:
        return images / config.sigma
    height, width = images.shape[-3:-1]
    spectral = jnp.fft.rfft2(images, axes=(-3, -2), norm="ortho") / jnp.sqrt(observation["spectrum"])
    return jnp.fft.irfft2(spectral, s=(height, width), axes=(-3, -2), norm="ortho")


def spectral_log_likelihood(observed, renders, observation: dict, config: LikelihoodConfig):
    """The spectral form's log likelihood of renders (B, h, w, 3) -> (B,) (module docstring)."""
    import jax.numpy as jnp

    residual = jnp.asarray(observed)[None] - renders
    spectral = jnp.fft.rfft2(residual, axes=(-3, -2), norm="ortho")
    quadratic = jnp.sum(observation["spectral_weight"] * (spectral.real ** 2 + spectral.imag ** 2), axis=(-3, -2, -1))
    return config.power * (-0.5 * quadratic - 0.5 * observation["spectral_log_det"])


def colour_log_likelihood(observed, renders, config: LikelihoodConfig, empty=None):
    """The colour log likelihood of the module docstring for a batch of renders (B, H, W, 3) -> (B,);
    with ``config.object_outlier``, pixels where a render differs from ``empty`` (the empty-floor
    render) have that outlier weight."""
    import jax.numpy as jnp

    from ..fit.noise import object_pixels, pixel_log_likelihood

    residual = jnp.asarray(observed)[None] - renders
    outlier = config.outlier
    if config.object_outlier is not None:
        outlier = jnp.where(object_pixels(renders, jnp.asarray(empty), xp=jnp), config.object_outlier, config.outlier)
    per_pixel = pixel_log_likelihood(residual, config.sigma, outlier, xp=jnp)
    return config.power * jnp.sum(per_pixel, axis=(-2, -1))


def observe(observed: np.ndarray, config: LikelihoodConfig, channels: list[Channel] | None = None,
            empty: np.ndarray | None = None, spectra: dict | None = None) -> dict:
    """What the likelihood needs of an observed image (H, W, 3): the image, for NP3 its selected
    VGG16 features, and for the spectral form the fitted spectrum of its size (``spectra``, keyed
    by (H, W)) with its weights and log-determinant. A pytree, so a compiled sampler takes it as an
    argument and serves every image of the same size without recompiling."""
    if config.kind == "np3" and not channels:
        from ..errors import MitsubaP3Error

        raise MitsubaP3Error("the np3 likelihood needs the fitted model's selected VGG16 channels")
    observation = {"image": np.asarray(observed, np.float32)}
    if config.object_outlier is not None or config.fields is not None:
        if empty is None:
            from ..errors import MitsubaP3Error

            raise MitsubaP3Error("a likelihood with an object outlier weight or shading fields needs the "
                                 "empty-floor render")
        observation["empty"] = np.asarray(empty, np.float32)
    if config.spectral:
        size = tuple(observation["image"].shape[:2])
        if not spectra or size not in spectra:
            from ..errors import MitsubaP3Error

            fitted = ", ".join(f"{h}x{w}" for h, w in (spectra or {})) or "none"
            raise MitsubaP3Error(f"the spectral noise form has no spectrum for {size[0]}x{size[1]} windows (fitted: "
                                 f"{fitted}); score at a fitted size or refit the model's noise stage")
        from ..fit.noise import rfft_multiplicity

        spectrum = np.asarray(spectra[size], np.float32)
        full = rfft_multiplicity(size[1])[None, :, None] * np.ones_like(spectrum)
        observation["spectrum"] = spectrum
        observation["spectral_weight"] = (full / spectrum).astype(np.float32)
        observation["spectral_log_det"] = np.float32(np.sum(full * np.log(2 * np.pi * spectrum.astype(np.float64))))
    if config.kind == "np3":
        observation["features"] = [np.asarray(f) for f in selected_features(observation["image"][None], channels)]
    return observation


def fields_masks(renders, objects, empty, regions: int = 2):
    """(..., R, h, w) the shading fields' regions of renders (..., h, w, 3) whose object covers ``objects``
    (..., h, w): the object's pixels, the floor the render changes from ``empty`` elsewhere (its shadow),
    and with ``regions`` 3 the rest of the floor (:data:`~mitsuba_p3.fit.fields.REGIONS`)."""
    import jax.numpy as jnp

    from ..fit.noise import object_pixels

    objects = jnp.asarray(objects, bool)
    changed = object_pixels(renders, jnp.asarray(empty), xp=jnp)
    masks = [objects, changed & ~objects] + ([~(changed | objects)] if regions == 3 else [])
    return jnp.stack(masks, axis=-3)


def fields_regions(config: LikelihoodConfig) -> int:
    """How many regions the config's shading fields cover (:func:`~mitsuba_p3.fit.fields.region_count`)."""
    from ..fit.fields import region_count

    if config.fields_object == "normals":
        from ..fit.irradiance import normal_regions

        return normal_regions(config.fields)
    return region_count(config.fields, config.fields_degree, config.fields_channels)


def fields_form(config: LikelihoodConfig, height: int, width: int, colours=None, xp=np):
    """(tau^2 per region and basis column (R, K), the monomials (h, w, k), the columns' channel loadings
    (K, k, 3)) of the config's shading fields (:mod:`mitsuba_p3.fit.fields`). Tinted fields' loadings are
    per region and object colour, (..., R, K, k, 3), and need the hypotheses' ``colours`` (..., 3)."""
    from ..errors import ConfigError
    from ..fit.fields import COLOURED, FieldsNoise, colour_tint, monomials

    if config.fields_object == "normals":         # the basis is each pose's own (fit.irradiance.region_bases)
        from ..fit.irradiance import column_variances, loading_for, normal_regions

        regions = normal_regions(config.fields)
        return (column_variances(config.fields, config.fields_channels, regions), None,
                loading_for(config.fields_channels, regions, colours, xp))
    noise = FieldsNoise(config.sigma, config.fields, config.fields_degree, config.power, (height, width),
                        config.fields_channels)
    if noise.channels in COLOURED:
        if colours is None:
            raise ConfigError(f"{noise.channels} shading fields need each hypothesis's object colour")
        loading = noise.loadings(colour_tint(colours, xp), xp)
    else:
        loading = noise.loadings()
    return noise.variances(), monomials(height, width, config.fields_degree), loading


def fields_parts(observed, renders, objects, empty, config: LikelihoodConfig, colours=None, normals=None):
    """(the fields' density at the fixed scale (B,), its quadratic form r' C_1^-1 r (B,)) of renders (B, h, w, 3)
    (:func:`fields_log_likelihood`'s arguments; the form is what the image's own scale reads)."""
    import jax.numpy as jnp

    from ..fit.fields import field_log_likelihood

    residual = jnp.asarray(observed)[None] - renders
    if config.fields_object == "normals":
        from ..errors import ConfigError
        from ..fit.irradiance import log_likelihood, normal_regions

        if normals is None:
            raise ConfigError("the shading fields on the object's normals need each render's normals")
        masks = fields_masks(renders, objects, empty, normal_regions(config.fields))
        return log_likelihood(residual, masks, normals, config.sigma, config.fields, config.fields_channels,
                              colours, xp=jnp, quadratic=True)
    variances, basis, loading = fields_form(config, *renders.shape[-3:-1], colours=colours, xp=jnp)
    masks = fields_masks(renders, objects, empty, fields_regions(config))
    return field_log_likelihood(residual, masks, config.sigma, variances, basis, xp=jnp, loading=loading,
                                quadratic=True)


def fields_log_likelihood(observed, renders, objects, empty, config: LikelihoodConfig, colours=None,
                          scale_weight=1.0, normals=None):
    """The shading fields' log likelihood of renders (B, h, w, 3) whose object covers ``objects`` (B, h, w)
    and, for tinted fields, is of colour ``colours`` (B, 3) -> (B,) (:mod:`mitsuba_p3.fit.fields`; the
    regions of :func:`fields_masks`). With ``config.scale``, the image's noise scale integrated out, at
    ``scale_weight`` w of the way from the fixed-scale density: (1 - w) log p_1 + w log p (the SMC's bridge)."""
    import jax.numpy as jnp

    from ..fit.fields import scale_log_likelihood

    value, form = fields_parts(observed, renders, objects, empty, config, colours, normals)
    if config.scale is None:
        return config.power * value
    count = config.scale[2] * np.prod(renders.shape[-3:])
    scaled = scale_log_likelihood(value, form, count, config.scale[:2], xp=jnp)
    return config.power * (value + scale_weight * (scaled - value))


def score(observation: dict, renders, config: LikelihoodConfig, channels: list[Channel] | None = None,
          objects=None, colours=None, normals=None):
    """(B, H, W, 3) renders -> (B,) log-likelihoods of ``observation`` (JAX). An observation's own
    ``neural_weight`` entry, a number the compiled sampler takes as an argument, overrides the
    config's: the SMC's bridge from P3 to NP3 tempers the neural term in by it; its ``scale_weight``
    does the same for the image's own noise scale (:func:`fields_log_likelihood`). The shading fields'
    form also needs the pixels each render's object covers, ``objects`` (B, H, W), and tinted fields
    the object's colour parameter, ``colours`` (B, 3)."""
    if config.fields is not None:
        if objects is None:
            from ..errors import ConfigError

            raise ConfigError("the shading fields' likelihood needs the renders' object pixels")
        log_lik = fields_log_likelihood(observation["image"], renders, objects, observation["empty"], config,
                                        colours, observation.get("scale_weight", 1.0), normals)
    elif config.spectral:
        log_lik = spectral_log_likelihood(observation["image"], renders, observation, config)
    else:
        log_lik = colour_log_likelihood(observation["image"], renders, config, observation.get("empty"))
    if config.kind == "np3":
        features = selected_features(renders, channels)
        weight = observation.get("neural_weight", config.neural_weight)
        log_lik = log_lik - weight * neural_distance(observation["features"], features)
    return log_lik


class ImageLikelihood:
    """log p(I | render) for a fixed observed image, batched over renders."""

    def __init__(self, observed: np.ndarray, config: LikelihoodConfig, channels: list[Channel] | None = None):
        self.config = config
        self.channels = channels or []
        self.observation = observe(observed, config, self.channels)

    def __call__(self, renders):
        """(B, H, W, 3) renders -> (B,) log-likelihoods (JAX)."""
        return score(self.observation, renders, self.config, self.channels)
