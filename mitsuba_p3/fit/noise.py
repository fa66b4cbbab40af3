"""The pixel noise model, fitted to the train split's residuals: what the colour likelihood is.

The residual of a pixel is r = observed - render (3 channels, [0, 1] images),
the render being the fitted Phong scene at the image's true geometry and fitted
material. The Phong model never matches a path-traced image exactly: soft
shadows, inter-reflections and texture detail leave residuals that are small
almost everywhere and large in a few places. So each pixel is

- an **inlier** with probability 1 - eps: its channels independent normals
  N(0, sigma^2) truncated to [-1, 1] (residuals of [0, 1] images cannot leave it), or
- an **outlier** with probability eps: uniform on [-1, 1]^3 (density 1/8),

and log p(r) = logaddexp(log(1 - eps) + sum_c log TN(r_c; 0, sigma), log eps - 3 log 2)
per pixel, summed over pixels (the per-pixel robust likelihood of Bayes3D / 3DP3).

**Where outliers are.** The outlier weight depends on what the render predicts at
the pixel: eps_object where the object (or its shadow) changes the render from
the empty floor, eps_floor elsewhere. At the true geometry a metal's reflections
are outliers the Phong model cannot explain, while the floor around an object
is nearly always explained. A single eps let the posterior call part of a metal
sphere "outliers" and explain the rest with a smaller sphere; with two, a pixel
the hypothesis leaves as floor but the image shows as object costs the price
of a floor outlier, which is high.

sigma and eps are fitted by EM (Dempster et al. 1977): the E-step gives each
pixel's inlier responsibility w, the M-step sets eps to the mean of 1 - w and
sigma^2 to the w-weighted mean squared channel residual (the exact M-step of an
untruncated normal; truncation at +-1 changes it by less than 1e-6 for sigma < 0.2).

**Which form infers.** Both forms are fitted; inference uses the Gaussian one
(eps = 0, sigma the residuals' root mean square: the maximum-likelihood normal) by
default. The mixture is the better description of the residuals at the *true*
geometry, but it is the worse *comparison* between hypotheses: it caps the cost of
a pixel the hypothesis gets wrong at -log(eps / 8) nats, so a smaller object that
leaves part of a metal sphere to "outliers" beats the whole sphere in a slightly
wrong shade, and the posterior shrinks metals. Chosen on train classes (the share of train
images whose most probable shape and size are right under each form, the same sampler otherwise).

**The footprint.** Where the observed image differs from the empty-floor render by
more than the floor's own residuals do, there is the object or its shadow. The
threshold is the 99.9th percentile of the largest channel |residual| over the
train split's floor pixels (where the fitted render is the empty floor); the
sampler starts its search there (:mod:`mitsuba_p3.infer.smc`).

**Correlation.** Neighbouring residuals are not independent (a misplaced edge
or a soft shadow spans many pixels), so the summed log likelihood counts each
piece of evidence several times and the posterior comes out over-confident. The
fit measures the residuals' spatial autocorrelation and its *correlation area*
A = sum of rho(lag) over lags up to 12 pixels in each direction (the
effective number of independent pixels is about N / A). The likelihood is raised
to the power beta = 1 / A, the magnitude adjustment of a composite likelihood
(Ribatet et al. 2012): the curvature of the summed log likelihood is then that
of N / A independent observations.

**The power along the pose (the sandwich form).** 1 / A is the right power for a
parameter whose effect on the image is a broad patch (a colour, a material weight):
its evidence is spread over the same area as the residuals' correlation. A pose or
size changes the image along the object's outline, a band a pixel or two wide, and
the residuals correlated with that band are those along the outline, not a whole
area: the evidence about the outline is repeated about a correlation *length*, not
an area. The composite likelihood's own adjustment says so exactly (Pauli et al.
2011; Ribatet et al. 2012): for the independence likelihood of residuals with
covariance C, the curvature along a direction g of the image (H = g'g / sigma^2)
and the variance of the score along it (J = g'Cg / sigma^4) give the power
beta = H / J = sigma^2 g'g / g'Cg, the "sandwich" H^-1 J made a scalar. The fit
takes g as the renders' finite differences along the object's x, y and size at the
train split's true geometry, and C as the residuals' covariance over lags up to 12
pixels, channels included, and pools beta = sum sigma^2 g'g / sum g'Cg. For white
residuals it is 1; it is 1 / A for a g as broad as the correlation.

**The correlated (spectral) form.** The power beta divides *all* the evidence by
A, the silhouette's included, although what is correlated is the low-frequency
mismatch of shading (soft shadows, rough highlights), not the outline. The
spectral form models the residual window r (h x w, per channel) instead as a
stationary Gaussian random field on the h x w torus: its orthonormal 2-D DFT
coefficients R(k) are independent with variances P(k), the field's power
spectrum (a circulant covariance: Whittle 1953). Then

    log p(r) = -1/2 sum_k |R(k)|^2 / P(k) - 1/2 sum_k log(2 pi P(k))

i.e. the residual is whitened by the filter 1 / sqrt(P) and scored as white
noise. The maximum-likelihood P from N residual windows is their mean
periodogram, which is what :func:`fit_spectra` computes, per channel, on windows
of the train split's residuals centred on the object (where the sampler scores:
:data:`SCORING_WINDOW`) and on whole images. Frequencies where the Phong model's
mismatch is large (low ones: blobs) get little weight; those where the fitted
renders match the images (high ones: a misplaced edge) keep theirs. Whitened
train residuals are close to white, and what correlation is left (mostly across
the three colour channels, which share a shading mismatch) gives this form's own
power, 1 / (its spatial correlation area x its colour-channel correlation area).
The spectrum can be shrunk towards white noise, P + lambda mean(P) rescaled to its
maximum-likelihood level (lambda = 0: the pure field; large lambda: the independent
Gaussian). The fit writes lambda = 1, the value measured on train images; the form
is not a default.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

OUTLIER_LOG_DENSITY = -3.0 * np.log(2.0)   # uniform on [-1, 1]^3
# the window (height, width) the SMC scores around the object by default (:mod:`mitsuba_p3.infer.smc`):
# the spectral noise form is fitted on train windows of this size (and on whole images)
SCORING_WINDOW = (56, 72)
SPECTRUM_FILE = "noise_spectrum.npz"
# lambda of the spectral form's shrinkage towards white noise (module docstring; measured, not tuned)
SPECTRAL_SHRINK = 1.0


@dataclass(frozen=True)
class NoiseModel:
    """A fitted pixel noise model (see the module docstring)."""

    sigma: float          # inlier scale per channel
    outlier: float        # eps_floor, the outlier probability of a pixel the render leaves as empty floor
    object_outlier: float | None = None   # eps_object, where the render differs from the empty floor
    power: float = 1.0    # beta, the likelihood power (1 / correlation area)
    shadows: bool = True  # the residuals came from renders with hard shadows (inference must match)
    gaussian_sigma: float | None = None   # the residuals' RMS per channel: sigma of the Gaussian form (eps = 0)
    footprint: float | None = None        # |observed - empty floor| above this marks the object or its shadow
    spectral_power: float | None = None   # the spectral form's power (None: no spectrum fitted)
    spectral_shrink: float | None = None  # lambda: the spectrum is P + lambda mean(P) (0: the pure field)
    pose_power: float | None = None       # the sandwich power along the pose (None: not fitted)
    fields: dict | None = None            # the shading fields' form (:class:`.fields.FieldsNoise` as a dict)
    normal_fields: dict | None = None     # the same on the object's normals (:mod:`.irradiance`; None: not fitted)

    def as_dict(self) -> dict:
        return asdict(self)


def truncation_log_mass(sigma: float) -> float:
    """log of the mass of N(0, sigma^2) inside [-1, 1]."""
    from scipy.special import log_ndtr, ndtr

    return float(np.log(ndtr(1.0 / sigma) - ndtr(-1.0 / sigma))) if sigma > 0.2 else float(
        np.log1p(-2.0 * np.exp(log_ndtr(-1.0 / sigma))))


def pixel_log_likelihood(residual, sigma: float, outlier, xp=np):
    """Per-pixel log p(r) of residuals (..., 3) under the inlier/outlier mixture (numpy or jax.numpy);
    ``outlier`` is a number or an array of per-pixel weights (...,)."""
    inlier = (-0.5 * xp.sum(residual * residual, axis=-1) / sigma ** 2
              - 3.0 * (np.log(sigma) + 0.5 * np.log(2 * np.pi) + truncation_log_mass(sigma)))
    if np.ndim(outlier) == 0 and outlier <= 0.0:
        return inlier
    return xp.logaddexp(xp.log1p(-outlier) + inlier, xp.log(outlier) + OUTLIER_LOG_DENSITY)


def object_pixels(renders, empty, xp=np):
    """Pixels (..., H, W) where a render differs from the empty-floor render: the object and its shadow."""
    return xp.any(xp.abs(renders - empty) > 1e-3, axis=-1)


def fit_mixture(residuals: np.ndarray, regions: np.ndarray | None = None, iterations: int = 200,
                tolerance: float = 1e-7, sigma: float = 0.05) -> tuple[float, np.ndarray, int]:
    """EM for sigma and one eps per region on residuals (N, ..., 3); ``regions`` (N, ...) holds each
    pixel's region index (default: one region). Returns (sigma, eps per region, iterations run)."""
    r = np.asarray(residuals, np.float64).reshape(-1, 3)
    region = np.zeros(len(r), int) if regions is None else np.asarray(regions, int).reshape(-1)
    count = region.max() + 1
    outlier = np.full(count, 0.05)
    squared = np.sum(r * r, axis=1)
    for step in range(1, iterations + 1):
        eps = outlier[region]
        inlier = np.log1p(-eps) + pixel_log_likelihood(r, sigma, 0.0)
        outlying = np.log(eps) + OUTLIER_LOG_DENSITY
        w = np.exp(inlier - np.logaddexp(inlier, outlying))               # inlier responsibilities
        new_outlier = np.clip(1.0 - np.bincount(region, w, count) / np.maximum(np.bincount(region, None, count), 1),
                              1e-6, 0.9)
        new_sigma = float(np.sqrt(np.sum(w * squared) / (3.0 * max(np.sum(w), 1e-12))))
        converged = abs(new_sigma - sigma) < tolerance and np.all(np.abs(new_outlier - outlier) < tolerance)
        sigma, outlier = new_sigma, new_outlier
        if converged:
            break
    return sigma, outlier, step


def correlation_area(residuals: np.ndarray, max_lag: int = 12) -> float:
    """The residual field's correlation area in pixels: the sum of its spatial autocorrelation rho over
    lags |dy|, |dx| <= max_lag (rho(0) = 1 included), pooled over images and channels; at least 1.

    Computed with FFTs on each (H, W) channel after removing its mean; >= 1 by construction."""
    r = np.asarray(residuals, np.float64)
    if r.ndim == 3:
        r = r[None]
    count, height, width, _ = r.shape
    r = r - r.mean(axis=(1, 2), keepdims=True)
    size = (2 * height, 2 * width)
    spectrum = np.fft.rfft2(r, s=size, axes=(1, 2))
    auto = np.fft.irfft2(np.abs(spectrum) ** 2, s=size, axes=(1, 2)).sum(axis=(0, 3))   # summed over images, channels
    overlap = np.fft.irfft2(np.abs(np.fft.rfft2(np.ones((height, width)), s=size)) ** 2, s=size)
    auto = auto / np.maximum(overlap, 1.0)                   # mean product per overlapping pixel pair
    rho = auto / auto[0, 0]
    lags = np.r_[0:max_lag + 1, -max_lag:0]
    window = rho[np.ix_(lags % size[0], lags % size[1])]
    return float(max(1.0, np.sum(window)))


def fit_noise(observations: np.ndarray, renders: np.ndarray, empty: np.ndarray, shadows: bool,
              windows: list[tuple[int, int]] | None = None, spectral_shrink: float = SPECTRAL_SHRINK,
              directions: np.ndarray | None = None, objects: np.ndarray | None = None,
              colours: np.ndarray | None = None, normals: np.ndarray | None = None) -> tuple[NoiseModel, dict, dict]:
    """The noise model of (observed, rendered) image pairs (N, H, W, 3), given the empty-floor render
    (H, W, 3), figures about the fit, and the spectral form's spectra per window size (``windows``,
    default :data:`SCORING_WINDOW`, and the whole image); ``shadows`` says whether the renders had hard
    shadows; ``directions`` (N, P, H, W, 3), the renders' changes along the pose, give the sandwich
    power (:func:`pose_power`); ``objects`` (N, H, W), the pixels each render's object covers, give the
    shading fields' form (:mod:`.fields`), fitted on the windows the sampler scores; tinted fields also
    need each render's object colour, ``colours`` (N, 3); the object's normals at the true geometry,
    ``normals`` (N, H, W, 3), give the fields on the normals (:mod:`.irradiance`) too."""
    residuals = np.asarray(observations, np.float64) - np.asarray(renders, np.float64)
    regions = object_pixels(np.asarray(renders), np.asarray(empty)).astype(int)     # 1: object or its shadow
    sigma, outlier, iterations = fit_mixture(residuals, regions)
    area = correlation_area(residuals)
    floor = np.abs(residuals).max(axis=-1)[regions == 0]
    sizes = list(dict.fromkeys([tuple(w) for w in (windows or [SCORING_WINDOW])] + [residuals.shape[1:3]]))
    spectra, spectral_power, spectral = fit_spectra(residuals, regions.astype(bool), sizes, spectral_shrink)
    model = NoiseModel(sigma=sigma, outlier=float(outlier[0]), object_outlier=float(outlier[-1]),
                       power=1.0 / area, shadows=shadows, gaussian_sigma=float(np.sqrt(np.mean(residuals ** 2))),
                       footprint=float(np.quantile(floor, 0.999)) if floor.size else None,
                       spectral_power=spectral_power, spectral_shrink=spectral_shrink,
                       pose_power=None if directions is None else pose_power(residuals, directions))
    fields_figures = None
    if objects is not None:
        from dataclasses import replace

        from .fields import COLOURED, FIT_CHANNELS, FIT_REGIONS, colour_tint, fit_fields

        if FIT_CHANNELS in COLOURED and colours is None:
            raise ValueError(f"{FIT_CHANNELS} shading fields are fitted with each train render's object colour")
        windows, masks, crops = field_windows(residuals, regions.astype(bool), np.asarray(objects, bool), sizes[0],
                                              FIT_REGIONS, crops=True)
        tints = None if colours is None else colour_tint(np.asarray(colours))
        fields, fields_figures = fit_fields(windows, masks, channels=FIT_CHANNELS, tints=tints)
        model = replace(model, fields=fields.as_dict())
        if normals is not None:
            from .irradiance import fit_normal_fields

            normal_windows = np.stack([np.asarray(normals[n])[crop] for n, crop in enumerate(crops)])
            normal, normal_figures = fit_normal_fields(windows, masks, normal_windows, FIT_CHANNELS, tints=tints)
            model = replace(model, normal_fields=normal.as_dict())
            fields_figures = {**fields_figures, "normals": normal_figures}
    figures = {"pixels": int(np.prod(residuals.shape[:-1])), "object_pixels": int(regions.sum()),
               "residual_rms": model.gaussian_sigma,
               "em_iterations": iterations, "correlation_area_pixels": area,
               "effective_sigma": model.gaussian_sigma / np.sqrt(model.power),
               "effective_sigma_mixture": sigma / np.sqrt(model.power), "spectral": spectral,
               "pose_power": model.pose_power,
               "effective_sigma_pose": None if model.pose_power is None else
               model.gaussian_sigma / np.sqrt(model.pose_power), "fields": fields_figures}
    return model, figures, spectra


def field_windows(residuals: np.ndarray, regions: np.ndarray, objects: np.ndarray,
                  size: tuple[int, int], count: int = 2, crops: bool = False) -> tuple:
    """The shading fields' training data: residual windows (N, h, w, 3) of ``size`` centred on each image's
    object and shadow (``regions``, (N, H, W)), and their region masks (N, ``count``, h, w): the object's
    pixels (``objects``), the rest of the footprint (its shadow), and with ``count`` 3 the rest of the floor;
    with ``crops``, also each window's (row, column) slices."""
    height, width = residuals.shape[1:3]
    size = (min(size[0], height), min(size[1], width))
    windows, masks, cuts = [], [], []
    for n in range(len(residuals)):
        top, left = window_around(regions[n], size)
        crop = (slice(top, top + size[0]), slice(left, left + size[1]))
        windows.append(residuals[n][crop])
        cuts.append(crop)
        masks.append(np.stack([objects[n][crop], regions[n][crop] & ~objects[n][crop],
                               ~(regions[n][crop] | objects[n][crop])][:count]))
    out = (np.stack(windows), np.stack(masks).astype(np.float64))
    return out + (cuts,) if crops else out


def window_around(mask: np.ndarray, size: tuple[int, int]) -> tuple[int, int]:
    """(top, left) of a ``size`` window centred on the bounding box of ``mask`` (H, W), kept inside the
    image (the image's centre for an empty mask)."""
    height, width = mask.shape
    rows, cols = np.nonzero(mask)
    if rows.size == 0:
        rows, cols = np.array([height // 2]), np.array([width // 2])
    top = int(np.clip((rows.min() + rows.max() + 1 - size[0]) // 2, 0, height - size[0]))
    left = int(np.clip((cols.min() + cols.max() + 1 - size[1]) // 2, 0, width - size[1]))
    return top, left


def rfft_multiplicity(width: int) -> np.ndarray:
    """How often each column of a real signal's ``rfft2`` stands in the full spectrum (width // 2 + 1,):
    1 for the zero and (even width) Nyquist columns, 2 for the others."""
    counts = np.full(width // 2 + 1, 2.0)
    counts[0] = 1.0
    if width % 2 == 0:
        counts[-1] = 1.0
    return counts


def periodogram(windows: np.ndarray) -> np.ndarray:
    """The mean periodogram (h, w // 2 + 1, 3) of residual windows (N, h, w, 3): the maximum-likelihood
    power spectrum of a stationary Gaussian field on the h x w torus, orthonormal DFT units (white
    noise of variance s^2 has P = s^2 everywhere)."""
    spectrum = np.fft.rfft2(np.asarray(windows, np.float64), axes=(1, 2), norm="ortho")
    return np.mean(np.abs(spectrum) ** 2, axis=0)


def whiten_numpy(windows: np.ndarray, spectrum: np.ndarray) -> np.ndarray:
    """Residual windows (N, h, w, 3) filtered by 1 / sqrt(P): white noise of variance 1 if the field
    has power spectrum ``spectrum``."""
    height, width = np.shape(windows)[1:3]
    spectral = np.fft.rfft2(np.asarray(windows, np.float64), axes=(1, 2), norm="ortho") / np.sqrt(spectrum)
    return np.fft.irfft2(spectral, s=(height, width), axes=(1, 2), norm="ortho")


def channel_correlation_area(residuals: np.ndarray) -> float:
    """The correlation area across colour channels: the mean over channels of the sum of their
    correlations with every channel (1 for independent channels, 3 for identical ones)."""
    flat = np.asarray(residuals, np.float64).reshape(-1, 3)
    return float(max(1.0, np.corrcoef(flat, rowvar=False).sum() / 3.0))


def fit_spectra(residuals: np.ndarray, regions: np.ndarray, sizes: list[tuple[int, int]],
                shrink: float = 0.0, floor: float = 1e-3) -> tuple[dict[tuple[int, int], np.ndarray], float, dict]:
    """The spectral noise form (module docstring) of residuals (N, H, W, 3) whose object pixels are
    ``regions`` (N, H, W): per window size, the mean periodogram of the windows centred on each image's
    object plus ``shrink`` x its mean (white noise: the shrinkage towards the independent form), floored
    at ``floor`` x its median so that no frequency gets an unbounded weight, and scaled to the level at
    which the whitened windows have variance 1 (the maximum-likelihood level of that shape); the form's
    power; and figures. The power and figures come from the first size's whitened windows."""
    residuals = np.asarray(residuals, np.float64)
    count, height, width, _ = residuals.shape
    spectra, figures = {}, {}
    for size in sizes:
        size = (min(size[0], height), min(size[1], width))
        corners = [window_around(regions[n], size) for n in range(count)]
        windows = np.stack([residuals[n, t:t + size[0], l:l + size[1]] for n, (t, l) in enumerate(corners)])
        spectrum = periodogram(windows)
        spectrum = spectrum + shrink * np.mean(spectrum, axis=(0, 1), keepdims=True)
        spectrum = np.maximum(spectrum, floor * np.median(spectrum, axis=(0, 1), keepdims=True))
        # the shrunk shape at its maximum-likelihood level: whitened windows of variance 1 per channel
        spectrum = spectrum * np.mean(whiten_numpy(windows, spectrum) ** 2, axis=(0, 1, 2))
        spectra[size] = spectrum.astype(np.float32)
        if len(spectra) == 1:
            white = whiten_numpy(windows, spectrum)
            spatial, channels = correlation_area(white), channel_correlation_area(white)
            figures = {"spectral_window": list(size), "shrink": shrink,
                       "raw_correlation_area_window": correlation_area(windows),
                       "whitened_correlation_area": spatial, "whitened_channel_correlation_area": channels,
                       "whitened_variance": float(np.mean(white ** 2)),
                       "low_to_high_power": float(spectrum[:3, :3].mean() / spectrum[size[0] // 4:3 * size[0] // 4,
                                                                                 size[1] // 4:].mean())}
    power = 1.0 / (figures["whitened_correlation_area"] * figures["whitened_channel_correlation_area"])
    return spectra, power, figures


def save_spectra(path, spectra: dict[tuple[int, int], np.ndarray]) -> None:
    from ..files import atomic_npz

    atomic_npz(path, **{f"{h}x{w}": value for (h, w), value in spectra.items()})


def load_spectra(path) -> dict[tuple[int, int], np.ndarray]:
    """The spectra of :func:`save_spectra`, keyed by window size; checked to be finite and positive."""
    out = {}
    with np.load(path, allow_pickle=False) as data:
        for key in data.files:
            h, w = (int(v) for v in key.split("x"))
            value = np.asarray(data[key], np.float32)
            if value.shape != (h, w // 2 + 1, 3) or not np.all(np.isfinite(value) & (value > 0)):
                raise ValueError(f"spectrum {key} has shape {value.shape} or non-positive values")
            out[h, w] = value
    return out


def _padded_spectra(fields: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """rfft2 of fields (N, H, W, C) zero-padded to ``size`` (no wrap-around within the lags used)."""
    return np.fft.rfft2(np.asarray(fields, np.float64), s=size, axes=(1, 2))


def lag_covariance(residuals: np.ndarray, max_lag: int = 12) -> np.ndarray:
    """The residuals' covariance C[dy, dx, c, c'] = E r_c(p) r_c'(p + (dy, dx)) over lags |dy|, |dx| <=
    max_lag, pooled over images, each image and channel centred: (2 L + 1, 2 L + 1, 3, 3), lag 0 at
    the centre."""
    r = np.asarray(residuals, np.float64)
    r = r - r.mean(axis=(1, 2), keepdims=True)
    count, height, width, channels = r.shape
    size = (2 * height, 2 * width)
    spectra = _padded_spectra(r, size)
    cross = np.fft.irfft2(np.einsum("nyxc,nyxd->yxcd", np.conj(spectra), spectra), s=size, axes=(0, 1))
    overlap = np.fft.irfft2(np.abs(np.fft.rfft2(np.ones((height, width)), s=size)) ** 2, s=size)
    cross = cross / (count * np.maximum(overlap, 1.0))[..., None, None]
    lags = np.r_[-max_lag:max_lag + 1]
    return cross[np.ix_(lags % size[0], lags % size[1])]


def pose_power(residuals: np.ndarray, directions: np.ndarray, max_lag: int = 12) -> float:
    """The sandwich power beta = sum sigma^2 g'g / sum g'Cg (module docstring) of image directions
    ``directions`` (N, P, H, W, 3) -- the renders' changes along P pose parameters of each of N
    images -- under the residuals' covariance over lags up to ``max_lag``. Clipped to 1, the power
    of independent residuals: no adjustment makes the likelihood sharper than that."""
    covariance = lag_covariance(residuals, max_lag)
    sigma2 = float(np.mean(np.diagonal(covariance[max_lag, max_lag])))
    g = np.asarray(directions, np.float64)
    g = g.reshape((-1,) + g.shape[2:])
    height, width = g.shape[1:3]
    size = (height + max_lag + 1, width + max_lag + 1)
    # the directions' own cross-correlation over lags, channels apart: A[dy, dx, c, c'] = sum_p g_c(p) g_c'(p + d),
    # accumulated over chunks of directions so that memory stays bounded at any resolution
    cross = 0.0
    for start in range(0, len(g), 64):
        spectra = _padded_spectra(g[start:start + 64], size)
        cross = cross + np.einsum("nyxc,nyxd->yxcd", np.conj(spectra), spectra)
    auto = np.fft.irfft2(cross, s=size, axes=(0, 1))
    lags = np.r_[-max_lag:max_lag + 1]
    auto = auto[np.ix_(lags % size[0], lags % size[1])]
    quadratic = float(np.sum(auto * covariance))
    return float(min(1.0, sigma2 * float(np.sum(g * g)) / max(quadratic, 1e-300)))
