"""Shading fields: the render's mismatch on the object's own pixels, marginalised.

The Phong model's residuals against a path tracer's images are correlated, and most of
the correlation is the object's own: a metal mirrors the floor and the sky, a rubber's
shading is softer than Phong's, a soft shadow's edge is wider than a hard one. The fitted Gaussian answers with one power
beta = 1 / A for the whole window (A the residuals' correlation area), which divides
the outline's evidence as much as the shading's; a stationary field (the spectral
form) discounts any blob anywhere, so an absent object borrows the blobs a metal
leaves. This form ties the correlation to what the hypothesis renders.

**The model.** Per colour channel the residual window r (P pixels) is

    r = B w + e,   w ~ N(0, diag(tau^2)),   e ~ N(0, sigma^2 I),

where B's columns are low-order polynomials of the pixel coordinates (constant and
linear by default, scaled to [-1, 1] over the window), each multiplied by a *region*
mask: the pixels the hypothesis renders as object, the floor its shadow darkens, and
(a third region, where the form has one) the rest of the window's floor, which carries
the image's own lighting where it differs from the fitted lights' (lights that move
from image to image, as CLEVR's do). Each region and polynomial degree has its own
tau. Integrating w out (Woodbury),

    log p(r) = -1/2 (r'r - sum_g b_g' (G_g + sigma^2 T_g^-1)^-1 b_g) / sigma^2
               - 1/2 sum_g log det(I + T_g G_g / sigma^2) - P/2 log(2 pi sigma^2),

with G_g = B_g'B_g and b_g = B_g'r for region g (the regions do not overlap, so the
regions' blocks are independent).

A field changes the object's shading smoothly; it cannot move the outline (it lives on
the rendered mask) and an absent object has no mask to carry one, so the outline and the
object's presence keep their evidence while a wrong shade costs little. The floor's field
is a plane across the whole floor: it can follow a change of lighting, not an object's
compact blob. The log-determinant is the fields' Occam factor: a larger mask has more
freedom and pays for it.

**Across the colour channels** (``channels``) the fields are ``independent`` (a field per
channel: any change of the object's colour is a constant field, so the form forgives a
wrong colour nearly as much as a wrong shade), ``achromatic`` (one field shared by the three
channels: it brightens or darkens, it cannot change a hue), or ``mixed`` (the constant
shared, the higher degrees per channel). A basis column is then a region mask times a
monomial times a channel loading (:func:`loadings`), and the Woodbury solve runs over the
columns of all three channels at once. ``tinted`` fields are achromatic on the floor's regions, and on
the object's own pixels load on the hypothesis's colour c as c / mean(c) (:func:`colour_tint`; a gray
object's loading is the achromatic one): they brighten or darken the object in its own colour, as an
error in the light it receives would, and cannot wash its colour out towards gray. An achromatic constant on a flat face is a gray offset that trades
freely against the colour's saturation, and the colour prior's pull to gray then desaturates a cube's or
a cylinder's colour. ``sheened`` fields are
tinted ones with a second, achromatic field on the object's pixels (its own taus, after the regions'):
a dielectric's white sheen is not the colour's, and tinted fields leave it to the specular weight. The
other regions' loadings are padded with zero columns, which the density ignores exactly (a zero
column adds nothing to the quadratic form, and log tau^2 + log(sigma^2 / tau^2) - log sigma^2 = 0 to
the Occam factor), so every region keeps one (R, K, k, 3) shape.

**The fit.** sigma and the taus maximise the marginal likelihood of the train split's
residual windows at the true geometry (:func:`fit_fields`; scipy's L-BFGS over their
logs). Whatever correlation the fields leave (the floor's path-tracing noise, the
outline's own mismatch) is handled as before, by a power: beta = 1 / (correlation area
of the residuals left after the fields' posterior mean), the composite likelihood's
magnitude adjustment for the remaining correlation.

**The power.** The correlation beta stands for is the white part's, so beta tempers the
pixels given the fields, and the fields keep their fitted prior:

    integral of N(r; B w, sigma^2 I)^beta N(w; 0, T) dw  =  const * N(r; 0, (sigma^2 / beta) I + B T B'),

the same density at a white scale sigma / sqrt(beta) (:attr:`FieldsNoise.white_sigma`) with
the taus as fitted; the constant is the same for every hypothesis of a window. Raising the
whole marginal to beta instead would temper the fields' prior too, as if their scales were
tau / sqrt(beta), so that the object's field can paint a sphere's shading onto a flat disc
for nearly nothing.

**An image's own scale.** sigma and the taus are the train split's, but an image the
model renders worse than its train images (a path tracer's metal, an object no primitive
fits, lights the fit never saw) leaves residuals several times larger, and at the train
scale every pose that explains a little more of them is then worth tens of nats: runs of
the same hypothesis settle on different isolated poses and the seeds disagree. The image's noise scale is therefore unknown, C = s^2 C_1 with C_1 =
(sigma^2 / beta) I + B T B' as above, and integrated out under a conjugate inverse-gamma
prior s^2 ~ IG(a, b):

    log p(r) = log p_1(r) + q / 2 - (a + n / 2) log(b + q / 2) + a log b - log G(a) + log G(a + n / 2),

with p_1 the density at s = 1, q = r' C_1^-1 r its quadratic form and n = beta x the
window's values its effective count (the composite likelihood's: under the fitted model q
is about n at the truth, so q / n is the window's own estimate of s^2). Two hypotheses of
one image then differ by about (q_2 - q_1) / (2 s^2) where their forms are close: the
evidence is tempered by the image's own misfit and not by the train split's, and where
the image is rendered as well as the train images (q / n about the prior's s^2) the
density is the fixed-scale one. The prior (a, b) maximises the marginal likelihood of the
train windows' forms at the truth, each s^2 times a chi-square of n degrees of freedom
(:func:`fit_scale`), so how much the scale may vary is the train split's, not a hand-set
constant (:func:`scale_log_likelihood`; ``--noise scaled``).

Everything here takes an array module ``xp`` (numpy for the fit, jax.numpy for the
sampler), and batches over leading axes.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, replace

import numpy as np

from ..small_linalg import cholesky, log_det, solve

REGIONS = ("object", "shadow", "floor")   # a form uses the first 2 or all 3 (older models: 2)
CHANNELS = ("independent", "achromatic", "mixed", "tinted", "sheened")
# the loadings whose object columns follow the hypothesis's colour (they need each hypothesis's colour)
COLOURED = ("tinted", "sheened")
# the loading the noise stage fits, chosen on train images: independent fields forgive a wrong colour;
# achromatic ones keep it but let a flat face's colour wash out towards gray; tinted ones explain the train
# residuals better and keep the colour; sheened ones fit better still and let a flat face's colour wash out again
FIT_CHANNELS = "tinted"
# how many of REGIONS the noise stage fits fields on (2: object and shadow; 3: and the rest of the floor)
FIT_REGIONS = 3
# where the likelihood's power acts (module docstring, "The power"): on the pixels given the fields; the form
# before 2026-11-27's second change raised the whole marginal to it. Evaluation folders and SBC caches record
# it, so that one made under the other form is refused rather than resumed
POWER_ON = "pixels"


@dataclass(frozen=True)
class FieldsNoise:
    """A fitted shading-fields noise model (module docstring)."""

    sigma: float               # the white part's scale per channel
    taus: tuple                # per region, per polynomial degree 0..degree (region-major)
    degree: int                # the polynomials' highest degree
    power: float               # 1 / the correlation area the fields leave
    window: tuple              # (height, width) of the windows it was fitted on
    channels: str = "independent"   # CHANNELS: how the fields load on r, g, b (module docstring)
    # the inverse-gamma prior (shape, rate) of an image's noise scale s^2 (module docstring, "An image's own
    # scale"), fitted on the same windows; None in models fitted before it
    scale: tuple | None = None
    # the object's basis: "pixels" (monomials of the pixel coordinates) or "normals" (the spherical harmonics
    # of its surface normals, :mod:`.irradiance`)
    object_basis: str = "pixels"

    @property
    def white_sigma(self) -> float:
        """The white part's scale in the likelihood: sigma / sqrt(power) (module docstring, "The power")."""
        return self.sigma / float(np.sqrt(self.power))

    def as_dict(self) -> dict:
        return {**asdict(self), "taus": list(self.taus), "window": list(self.window),
                "scale": None if self.scale is None else list(self.scale)}

    @classmethod
    def from_dict(cls, d: dict) -> "FieldsNoise":
        return cls(sigma=float(d["sigma"]), taus=tuple(float(t) for t in d["taus"]), degree=int(d["degree"]),
                   power=float(d["power"]), window=tuple(int(v) for v in d["window"]),
                   channels=str(d.get("channels", "independent")),
                   scale=None if d.get("scale") is None else tuple(float(v) for v in d["scale"]),
                   object_basis=str(d.get("object_basis", "pixels")))

    def variances(self) -> np.ndarray:
        """(regions, K) tau^2 of every basis column (:func:`loadings`' columns)."""
        if self.object_basis == "normals":
            from .irradiance import column_variances as normal_variances

            return normal_variances(self.taus, self.channels, self.regions)
        return column_variances(self.taus, self.degree, self.channels)

    def loadings(self, tint=None, xp=np):
        """(K, k, 3) the basis columns' loadings (:func:`loadings`); for ``tinted`` and ``sheened`` fields,
        per region (..., R, K, k, 3) given the object's ``tint`` (..., 3) (:func:`tinted_loadings`)."""
        base = loadings(self.degree, self.channels)
        if self.channels not in COLOURED:
            return base
        if tint is None:
            raise ValueError(f"{self.channels} shading fields need the object's tint (colour_tint of its colour)")
        return tinted_loadings(base, tint, self.regions, xp, sheen=self.channels == "sheened")

    @property
    def regions(self) -> int:
        """How many of :data:`REGIONS` the form has fields on."""
        if self.object_basis == "normals":
            from .irradiance import normal_regions

            return normal_regions(self.taus)
        return region_count(self.taus, self.degree, self.channels)


def region_count(taus, degree: int, channels: str = "independent") -> int:
    """How many of :data:`REGIONS` a form with ``taus`` (region-major, degrees 0..``degree``; ``sheened``
    fields' sheen taus after them) covers; a ValueError unless that is 2 or 3 whole regions."""
    regions, rest = divmod(len(taus) - (degree + 1 if channels == "sheened" else 0), degree + 1)
    if rest or regions not in (2, 3):
        raise ValueError(f"the shading fields need 2 or 3 regions x {degree + 1} degrees of scales"
                         f"{' and a sheen' if channels == 'sheened' else ''}; got {len(taus)}")
    return regions


def _degrees(degree: int) -> np.ndarray:
    """(k,) the total degree of each monomial of :func:`monomials`."""
    return np.array([total for total in range(degree + 1) for _ in range(total + 1)])


def _degree_of(monomial_count: int) -> int:
    """The highest degree d of :func:`monomials` that make ``monomial_count`` = (d + 1)(d + 2) / 2 of them."""
    return int(round((np.sqrt(8 * monomial_count + 1) - 3) / 2))


def loadings(degree: int, channels: str = "independent") -> np.ndarray:
    """(K, k, 3): basis column j of a region is sum over monomials m and channels c of L[j, m, c] times
    the region's mask times monomial m in channel c. ``independent``: a column per monomial and
    channel; ``achromatic``: a column per monomial, the same in the three channels; ``mixed``: the
    constant achromatic, the other monomials per channel; ``tinted`` and ``sheened``: the achromatic
    columns, which :func:`tinted_loadings` colours on the object's region."""
    return function_loadings(_degrees(degree), channels)


def function_loadings(degrees, channels: str) -> np.ndarray:
    """(K, k, 3) :func:`loadings` over k basis functions of the given ``degrees`` (k,) (the monomials', or the
    spherical harmonics' bands): a column per function shared by the channels or one per channel (``mixed``:
    the degree-0 function shared, the others per channel)."""
    if channels not in CHANNELS:
        raise ValueError(f"unknown fields channels {channels!r}; choose {', '.join(CHANNELS)}")
    columns = []
    for m, total in enumerate(degrees):
        shared = channels in ("achromatic",) + COLOURED or (channels == "mixed" and total == 0)
        for c in ([None] if shared else range(3)):
            column = np.zeros((len(degrees), 3))
            column[m, slice(None) if c is None else c] = 1.0
            columns.append(column)
    return np.stack(columns)


def colour_tint(colour, xp=np):
    """(..., 3) the tint of an object of colour ``colour`` (..., 3), clipped to [0, 1] as the renderer
    reads it, scaled so that its channels' mean is 1 (a gray object's tint is (1, 1, 1), the achromatic
    loading); black: (1, 1, 1)."""
    colour = xp.clip(xp.asarray(colour), 0.0, 1.0)
    mean = xp.mean(colour, axis=-1, keepdims=True)
    return xp.where(mean > 1e-6, colour / xp.maximum(mean, 1e-6), xp.ones_like(colour))


def tinted_loadings(base, tint, regions: int, xp=np, sheen: bool = False):
    """(..., R, K, k, 3) per-region loadings of ``tinted`` fields: the object's region (the first) the
    achromatic ``base`` (K, k, 3) times ``tint`` (..., 3) channel by channel, the other regions ``base``.
    With ``sheen`` (``sheened`` fields), (..., R, 2K, k, 3): the object's region also ``base`` itself, the
    other regions ``base`` and K zero columns (module docstring)."""
    base = xp.asarray(base)
    tint = xp.asarray(tint, base.dtype)
    coloured = base * tint[..., None, None, :]                                          # (..., K, k, 3)
    plain = xp.broadcast_to(base, coloured.shape)
    if sheen:
        coloured = xp.concatenate([coloured, plain], axis=-3)
        plain = xp.concatenate([plain, xp.zeros_like(plain)], axis=-3)
    return xp.stack([coloured] + [plain] * (regions - 1), axis=-4)


def per_region(loading, regions: int, xp=np):
    """``loading`` as per-region loadings (..., R, K, k, 3): one shared by the regions (K, k, 3) repeated
    ``regions`` times, a per-region one (tinted fields') as it is."""
    loading = xp.asarray(loading)
    return xp.broadcast_to(loading, (regions,) + loading.shape) if loading.ndim == 3 else loading


def column_variances(taus, degree: int, channels: str = "independent") -> np.ndarray:
    """(regions, K) tau^2 of each basis column of :func:`loadings`: its region's tau at its monomial's degree
    (``sheened``: (regions, 2K), the object's sheen columns at the sheen's taus, the other regions' zero
    columns at 1, which the density ignores)."""
    per = _degrees(degree)
    regions = region_count(taus, degree, channels)
    taus = np.asarray(taus, np.float64)
    column_degree = np.array([per[np.nonzero(column.any(axis=1))[0][0]] for column in loadings(degree, channels)])
    variances = taus[:regions * (degree + 1)].reshape(regions, degree + 1)[:, column_degree] ** 2
    if channels != "sheened":
        return variances
    sheen = np.ones_like(variances)
    sheen[0] = taus[regions * (degree + 1):][column_degree] ** 2
    return np.concatenate([variances, sheen], axis=1)


def monomials(height: int, width: int, degree: int) -> np.ndarray:
    """(h, w, k) the monomials u^i v^j, i + j <= ``degree``, of pixel coordinates scaled to [-1, 1] across
    the window (u along columns, v along rows), ordered by total degree."""
    v, u = np.meshgrid(np.linspace(-1.0, 1.0, height), np.linspace(-1.0, 1.0, width), indexing="ij")
    return np.stack([u ** i * v ** (total - i) for total in range(degree + 1) for i in range(total + 1)], axis=-1)


def field_statistics(residual, masks, basis, xp=np) -> tuple:
    """What the density needs of residual windows (..., h, w, 3) and their region masks (..., R, h, w):
    (r'r (...,), G (..., R, k, k), b = B'r (..., R, k, 3), the number of values per window). The fit
    computes them once; the density is then small linear algebra per window."""
    residual = xp.asarray(residual)
    masks = xp.asarray(masks, residual.dtype)
    basis = xp.asarray(basis, residual.dtype)
    height, width, k = basis.shape
    pixels = masks.reshape(masks.shape[:-2] + (height * width,))                      # (..., R, P)
    products = (basis[..., :, None] * basis[..., None, :]).reshape(height * width, k * k)
    gram = (pixels @ products).reshape(pixels.shape[:-1] + (k, k))
    flat = residual.reshape(residual.shape[:-3] + (height * width, 3))
    weighted = basis.reshape(height * width, k)[None, :, :] * pixels[..., :, None]        # (..., R, P, k)
    projected = xp.swapaxes(weighted, -1, -2) @ flat[..., None, :, :]                  # (..., R, k, 3)
    return xp.sum(residual * residual, axis=(-3, -2, -1)), gram, projected, height * width * 3


def column_statistics(statistics: tuple, loading, xp=np) -> tuple:
    """:func:`field_statistics` over the basis columns of ``loading`` (K, k, 3), or per region and window
    (..., R, K, k, 3): (r'r, G (..., R, K, K), b (..., R, K), count). Columns in different channels are
    orthogonal; each channel's monomials share the per-channel Gram matrix."""
    squares, gram, projected, count = statistics
    loading = xp.asarray(loading, gram.dtype)
    if loading.ndim > 3:            # per region (and per window): tinted fields (..., R, K, k, 3)
        full = xp.einsum("...rjmc,...rinc,...rmn->...rji", loading, loading, gram)
        return squares, full, xp.einsum("...rjmc,...rmc->...rj", loading, projected), count
    full = xp.einsum("jmc,inc,...mn->...ji", loading, loading, gram)
    return squares, full, xp.einsum("jmc,...mc->...j", loading, projected), count


def marginal_log_likelihood(statistics: tuple, sigma: float, variances, xp=np, solved: bool = False,
                            loading=None, quadratic: bool = False):
    """log p(r) (...,) from :func:`field_statistics` under ``sigma`` and the fields' ``variances`` (R, K) of
    the columns of ``loading`` (K, k, 3; default: independent channels); with ``solved``, also the fields'
    posterior means (..., R, K); with ``quadratic``, also r' C^-1 r (...,), C = sigma^2 I + B T B' (the
    scale's sufficient statistic, :func:`scale_log_likelihood`)."""
    gram = statistics[1]
    if loading is None:
        loading = loadings(_degree_of(gram.shape[-1]))
    squares, gram, projected, count = column_statistics(statistics, loading, xp)
    size = gram.shape[-1]
    eye = xp.eye(size, dtype=gram.dtype)
    variances = xp.asarray(variances, gram.dtype)
    # one Cholesky factor of M = G + sigma^2 T^-1 gives the fields' means M^-1 b and the Occam factor:
    # det(I + T G / sigma^2) = det(T) det(M) / sigma^(2K) (no LAPACK call: :mod:`mitsuba_p3.small_linalg`)
    factor = cholesky(gram + (sigma ** 2 / variances)[..., None] * eye, xp)
    means = solve(factor, projected, xp)
    form = (squares - xp.sum(projected * means, axis=(-2, -1))) / sigma ** 2
    logdet = xp.sum(xp.log(variances), axis=-1) + log_det(factor, xp) - size * np.log(sigma ** 2)   # (..., R)
    value = -0.5 * form - 0.5 * xp.sum(logdet, axis=-1) - 0.5 * count * np.log(2 * np.pi * sigma ** 2)
    if not (solved or quadratic):
        return value
    return (value,) + ((means,) if solved else ()) + ((form,) if quadratic else ())


def field_log_likelihood(residual, masks, sigma: float, variances, basis, xp=np, left: bool = False, loading=None,
                         quadratic: bool = False):
    """log p(r) of residual windows (..., h, w, 3) whose region masks are ``masks`` (..., R, h, w) under
    the fields of ``variances`` (R, K) tau^2, ``basis`` (h, w, k) and ``loading`` (K, k, 3; default:
    independent channels) (module docstring) -> (...,). With ``left``, also the residual the fields'
    posterior mean leaves (..., h, w, 3); with ``quadratic`` (not with ``left``), also r' C^-1 r (...,)."""
    if loading is None:
        loading = loadings(_degree_of(np.shape(basis)[-1]))
    statistics = field_statistics(residual, masks, basis, xp)
    if quadratic and not left:
        return marginal_log_likelihood(statistics, sigma, variances, xp, loading=loading, quadratic=True)
    value, means = marginal_log_likelihood(statistics, sigma, variances, xp, solved=True, loading=loading)
    if not left:
        return value
    loading = per_region(xp.asarray(loading, means.dtype), np.shape(masks)[-3], xp)
    mean_field = xp.einsum("...rhw,hwm,...rjmc,...rj->...hwc", xp.asarray(masks, means.dtype),
                           xp.asarray(basis, means.dtype), loading, means)
    return value, xp.asarray(residual) - mean_field


def scale_log_likelihood(value, form, count: float, scale: tuple, xp=np):
    """log p(r) with the image's noise scale integrated out (module docstring, "An image's own scale"), from
    the density at scale 1, ``value`` (...,), its quadratic form r' C^-1 r, ``form`` (...,), the window's
    effective count of values ``count`` (power x values) and the scale's inverse-gamma prior ``scale``
    (shape, rate)."""
    from scipy.special import gammaln

    shape, rate = (float(v) for v in scale)
    half = 0.5 * float(count)
    constant = shape * np.log(rate) - gammaln(shape) + gammaln(shape + half)
    return value + 0.5 * form - (shape + half) * xp.log(rate + 0.5 * form) + constant


def fit_scale(forms: np.ndarray, counts) -> tuple[float, float]:
    """The inverse-gamma prior (shape, rate) of the noise scale s^2 that maximises the marginal likelihood
    of the windows' quadratic forms ``forms`` (N,), each s^2 times a chi-square of ``counts`` (N,) effective
    degrees of freedom (module docstring, "An image's own scale")."""
    from scipy.optimize import minimize
    from scipy.special import gammaln

    forms = np.asarray(forms, np.float64)
    half = 0.5 * np.broadcast_to(np.asarray(counts, np.float64), forms.shape)
    if forms.size < 2 or not np.all(np.isfinite(forms) & (forms > 0)):
        raise ValueError("the scale's prior is fitted on two or more windows with positive quadratic forms")

    def negative(log_params):
        shape, rate = np.exp(log_params)
        return -float(np.sum(shape * np.log(rate) + gammaln(shape + half) - gammaln(shape) - gammaln(half)
                             + (half - 1) * np.log(0.5 * forms) - (shape + half) * np.log(rate + 0.5 * forms)))

    ratio = forms / (2 * half)                          # each window's own estimate of s^2
    mean, var = float(np.mean(ratio)), float(np.var(ratio)) + 1e-12
    shape = 2.0 + mean ** 2 / var                       # the moments' inverse gamma, where the optimiser starts
    best = minimize(negative, np.log([shape, mean * (shape - 1)]), method="L-BFGS-B",
                    bounds=[(np.log(1e-2), np.log(1e6))] * 2)
    return tuple(float(v) for v in np.exp(best.x))


def sample_fields(masks, variances, basis, rng: np.random.Generator, loading=None) -> np.ndarray:
    """One draw of the fields B w (h, w, 3) on region masks (R, h, w): w ~ N(0, ``variances``) (R, K) over
    the columns of ``basis`` (h, w, k) and ``loading`` (K, k, 3, or per region (R, K, k, 3); default:
    independent channels); with white noise of the form's sigma added, a residual window the model would
    make (simulation-based calibration simulates its images so)."""
    if loading is None:
        loading = loadings(_degree_of(np.shape(basis)[-1]))
    variances = np.asarray(variances, np.float64)
    weights = rng.standard_normal(variances.shape) * np.sqrt(variances)
    loading = per_region(np.asarray(loading, np.float64), variances.shape[0])
    return np.einsum("rhw,hwm,rjmc,rj->hwc", np.asarray(masks, np.float64), np.asarray(basis, np.float64),
                     loading, weights)


def fit_fields(residuals: np.ndarray, masks: np.ndarray, degree: int = 1,
               channels: str = "independent", tints: np.ndarray | None = None) -> tuple[FieldsNoise, dict]:
    """The fields model of residual windows (N, h, w, 3) with region masks (N, R, h, w), by maximum marginal
    likelihood (module docstring), and figures: the correlation area before and after the fields. ``tinted``
    and ``sheened`` fields need each window's object ``tints`` (N, 3) (:func:`colour_tint` of its colour)."""
    from scipy.optimize import minimize

    from .noise import correlation_area

    residuals = np.asarray(residuals, np.float64)
    masks = np.asarray(masks, np.float64)
    height, width = residuals.shape[1:3]
    basis = monomials(height, width, degree)
    loading = loadings(degree, channels)
    if channels in COLOURED:
        if tints is None or len(tints) != len(residuals):
            raise ValueError(f"{channels} shading fields are fitted with each window's object tint (colour_tint)")
        loading = tinted_loadings(loading, np.asarray(tints, np.float64), masks.shape[1], sheen=channels == "sheened")
    groups = (masks.shape[1] + (channels == "sheened")) * (degree + 1)

    def model(log_params) -> FieldsNoise:
        return FieldsNoise(float(np.exp(log_params[0])), tuple(np.exp(log_params[1:]).tolist()), degree, 1.0,
                           (height, width), channels)

    statistics = field_statistics(residuals, masks, basis)          # once: the density is then small algebra

    def negative(log_params):
        noise = model(log_params)
        return -float(np.sum(marginal_log_likelihood(statistics, noise.sigma, noise.variances(), loading=loading)))

    start = np.r_[np.log(np.sqrt(np.mean(residuals ** 2))), np.full(groups, np.log(0.05))]
    best = minimize(negative, start, method="L-BFGS-B", bounds=[(np.log(1e-4), 0.0)] * len(start))
    noise = model(best.x)
    _, left = field_log_likelihood(residuals, masks, noise.sigma, noise.variances(), basis, left=True, loading=loading)
    before, after = correlation_area(residuals), correlation_area(left)
    noise = FieldsNoise(noise.sigma, noise.taus, degree, 1.0 / after, (height, width), channels)
    # each window's quadratic form at the likelihood's white scale gives the image's own scale (module docstring)
    _, forms = marginal_log_likelihood(statistics, noise.white_sigma, noise.variances(), loading=loading,
                                       quadratic=True)
    count = noise.power * statistics[3]
    noise = replace(noise, scale=fit_scale(forms, count))
    ratios = forms / count
    figures = {"sigma": noise.sigma, "taus": list(noise.taus), "degree": degree, "channels": channels,
               "power": noise.power, "scale": list(noise.scale),
               "scale_ratio_quantiles": {str(q): float(np.quantile(ratios, q)) for q in (0.1, 0.5, 0.9, 0.99)},
               "correlation_area_window": before, "correlation_area_after_fields": after,
               "log_likelihood_per_pixel": -float(best.fun) / (residuals.size / 3), "optimiser": str(best.message)}
    return noise, figures
