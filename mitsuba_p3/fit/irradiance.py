"""Shading fields on the object's normals: its image's own lighting as a nuisance, integrated out.

The shading fields (:mod:`.fields`) give the object's pixels smooth corrections in *pixel* coordinates (a
constant and a gradient across the window). A flat silhouette plus a gradient then mimics a ball's shading,
so a squat drum placed further back can explain a sphere's image as well as the sphere does, and a lamp that
moves from image to image (CLEVR's are jittered per image) is exactly what such a correction must absorb.

Here the object's correction is a function of its surface **normal** instead. For a convex Lambertian
surface under any distant lighting, irradiance is a smooth function E(n) of the normal that the real
spherical harmonics of degree <= 2 represent to within a few per cent (Ramamoorthi and Hanrahan 2001, "An
efficient representation for irradiance environment maps"): nine coefficients. The residual on the object's
pixels is modelled as

    r(p) = sum_j w_j Y_j(n(p)) (times the fields' channel loading, e.g. the object's tint) + e,

with w ~ N(0, tau_l^2) per band l = 0, 1, 2 and the other regions (shadow, floor) as in :mod:`.fields`. The
coefficients are integrated out in closed form, as the pixel fields are. A hypothesis earns the correction
only through *its own* normals: a sphere's normals span the visible hemisphere smoothly, a cylinder's are one
normal on its top and a band of horizontal ones on its side, so a cylinder cannot borrow a ball's shading
gradient across its top face, and a flat face stays flat.

Everything takes an array module ``xp`` (numpy for the fit, jax.numpy for the sampler).
"""
from __future__ import annotations

import numpy as np

from .fields import (COLOURED, FieldsNoise, _degrees, colour_tint, fit_scale, marginal_log_likelihood, monomials,
                     tinted_loadings)
from .fields import function_loadings as fields_function_loadings

# the spherical-harmonic band of each basis function of :func:`irradiance_basis`
SH_BANDS = np.array([0, 1, 1, 1, 2, 2, 2, 2, 2])
FUNCTIONS = len(SH_BANDS)


def irradiance_basis(normals, xp=np):
    """(..., 9) the real spherical harmonics of degree <= 2 of unit ``normals`` (..., 3), unnormalised (the
    fields' scales absorb each band's constant)."""
    normals = xp.asarray(normals)
    x, y, z = normals[..., 0], normals[..., 1], normals[..., 2]
    return xp.stack([xp.ones_like(x), x, y, z, x * y, y * z, x * z, x * x - y * y, 3 * z * z - 1], axis=-1)


def region_bases(normals, masks_shape, xp=np):
    """(..., R, h, w, 9) each region's basis functions: the object's (the first region) the harmonics of its
    ``normals`` (..., h, w, 3), every other region the window's monomials of degree <= 1 padded with zero
    functions (which the density ignores exactly, :mod:`.fields`)."""
    regions, height, width = masks_shape[-3:]
    harmonics = irradiance_basis(normals, xp)                                          # (..., h, w, 9)
    plane = xp.asarray(monomials(height, width, 1), harmonics.dtype)                    # (h, w, 3)
    plane = xp.concatenate([plane, xp.zeros((height, width, FUNCTIONS - plane.shape[-1]), harmonics.dtype)], -1)
    plane = xp.broadcast_to(plane, harmonics.shape)
    return xp.stack([harmonics] + [plane] * (regions - 1), axis=-4)


def function_loadings(channels: str) -> np.ndarray:
    """(K, 9, 3) the basis columns' loadings on the nine harmonics (:func:`.fields.function_loadings`)."""
    return fields_function_loadings(SH_BANDS, channels)


def column_variances(taus, channels: str, regions: int) -> np.ndarray:
    """(R, K) tau^2 of each column: the object's by its function's band (``taus[:3]``), every other region's
    by its monomial's degree (``taus[3 + 2 r : 5 + 2 r]``), the zero functions' at 1."""
    taus = np.asarray(taus, np.float64)
    if len(taus) != 3 + 2 * (regions - 1):
        raise ValueError(f"normal fields over {regions} regions need {3 + 2 * (regions - 1)} scales; got {len(taus)}")
    loading = function_loadings(channels)
    function_of = np.array([np.nonzero(column.any(axis=1))[0][0] for column in loading])
    rows = [taus[SH_BANDS[function_of]] ** 2]
    # the other regions' functions: the plane's monomials (degrees 0, 1, 1), then zero functions (-1)
    degree = np.r_[_degrees(1), np.full(FUNCTIONS - len(_degrees(1)), -1)][function_of]
    for r in range(regions - 1):
        own = taus[3 + 2 * r: 5 + 2 * r]
        rows.append(np.where(degree >= 0, own[np.maximum(degree, 0)] ** 2, 1.0))
    return np.stack(rows)


def normal_regions(taus) -> int:
    """How many regions a normal form's ``taus`` cover (3 object bands, then two scales per other region)."""
    regions, rest = divmod(len(taus) - 3, 2)
    if rest or regions + 1 not in (2, 3):
        raise ValueError(f"normal fields need 3 + 2 per other region scales; got {len(taus)}")
    return regions + 1


def statistics(residual, masks, bases, xp=np) -> tuple:
    """:func:`.fields.field_statistics` with a basis per region and window, ``bases`` (..., R, h, w, k)."""
    residual = xp.asarray(residual)
    masks = xp.asarray(masks, residual.dtype)
    bases = xp.asarray(bases, residual.dtype)
    weighted = bases * masks[..., None]                                                 # (..., R, h, w, k)
    gram = xp.einsum("...rhwi,...rhwj->...rij", weighted, bases)
    projected = xp.einsum("...rhwi,...hwc->...ric", weighted, residual)
    height, width = residual.shape[-3:-1]
    return xp.sum(residual * residual, axis=(-3, -2, -1)), gram, projected, height * width * 3


def loading_for(channels: str, regions: int, colours=None, xp=np):
    """The columns' loadings (K, 9, 3), or per region and hypothesis for tinted fields (..., R, K, 9, 3)."""
    base = function_loadings(channels)
    if channels not in COLOURED:
        return base
    if colours is None:
        raise ValueError(f"{channels} normal fields need each hypothesis's object colour")
    return tinted_loadings(base, colour_tint(colours, xp), regions, xp, sheen=channels == "sheened")


def log_likelihood(residual, masks, normals, sigma: float, taus, channels: str, colours=None, xp=np,
                   quadratic: bool = False):
    """log p(r) (...,) of residual windows (..., h, w, 3) with region masks (..., R, h, w) and the object's
    normals (..., h, w, 3); with ``quadratic``, also r' C^-1 r (the image's own scale reads it)."""
    regions = np.shape(masks)[-3]
    bases = region_bases(normals, np.shape(masks), xp)
    loading = loading_for(channels, regions, colours, xp)
    return marginal_log_likelihood(statistics(residual, masks, bases, xp), sigma,
                                   column_variances(taus, channels, regions), xp, loading=loading,
                                   quadratic=quadratic)


def fit_normal_fields(residuals: np.ndarray, masks: np.ndarray, normals: np.ndarray, channels: str = "tinted",
                      tints: np.ndarray | None = None) -> tuple[FieldsNoise, dict]:
    """The normal fields of residual windows (N, h, w, 3), region masks (N, R, h, w) and the true geometry's
    normals (N, h, w, 3), by maximum marginal likelihood; the power of the correlation they leave and the
    image scale's prior as :func:`.fields.fit_fields` fits them. Returns the form and figures."""
    from scipy.optimize import minimize

    from .noise import correlation_area

    residuals = np.asarray(residuals, np.float64)
    masks = np.asarray(masks, np.float64)
    regions = masks.shape[1]
    height, width = residuals.shape[1:3]
    loading = function_loadings(channels)
    if channels in COLOURED:
        if tints is None or len(tints) != len(residuals):
            raise ValueError(f"{channels} normal fields are fitted with each window's object tint (colour_tint)")
        loading = tinted_loadings(loading, np.asarray(tints, np.float64), regions, sheen=channels == "sheened")
    bases = region_bases(np.asarray(normals, np.float64), masks.shape)
    stats = statistics(residuals, masks, bases)

    def negative(log_params):
        sigma, taus = float(np.exp(log_params[0])), np.exp(log_params[1:])
        return -float(np.sum(marginal_log_likelihood(stats, sigma, column_variances(taus, channels, regions),
                                                     loading=loading)))

    start = np.r_[np.log(np.sqrt(np.mean(residuals ** 2))), np.full(3 + 2 * (regions - 1), np.log(0.05))]
    best = minimize(negative, start, method="L-BFGS-B", bounds=[(np.log(1e-4), 0.0)] * len(start))
    sigma, taus = float(np.exp(best.x[0])), tuple(np.exp(best.x[1:]).tolist())
    variances = column_variances(taus, channels, regions)
    _, means = marginal_log_likelihood(stats, sigma, variances, solved=True, loading=loading)
    per_region = np.broadcast_to(loading, (len(residuals), regions) + loading.shape[-3:]) if loading.ndim == 3 \
        else loading
    mean_field = np.einsum("nrhw,nrhwm,nrjmc,nrj->nhwc", masks, bases, per_region, means)
    after = correlation_area(residuals - mean_field)
    noise = FieldsNoise(sigma, taus, 1, 1.0 / after, (height, width), channels, object_basis="normals")
    _, forms = marginal_log_likelihood(stats, noise.white_sigma, variances, loading=loading, quadratic=True)
    count = noise.power * stats[3]
    noise = FieldsNoise(sigma, taus, 1, noise.power, (height, width), channels, fit_scale(forms, count), "normals")
    figures = {"sigma": sigma, "taus": list(taus), "channels": channels, "object_basis": "normals",
               "power": noise.power, "correlation_area_window": correlation_area(residuals),
               "correlation_area_after_fields": after,
               "log_likelihood_per_pixel": -float(best.fun) / (residuals.size / 3), "optimiser": str(best.message)}
    return noise, figures
