"""Where the object is: a data-driven proposal for the position, from the image's footprint.

Drawn from the prior, almost no position lands on the object: the floor is
0.28 m wide and a small object 0.035 m. But the image shows where the object is.
Where the observed image differs from the fitted empty-floor render by more than
the floor's own residuals do (the threshold fitted with the noise model,
:mod:`mitsuba_p3.fit.noise`), there is the object or its shadow: its *footprint*.

A pixel of the object's surface lies within about one half-extent of the object's
centre, which sits at the height of its vertical half-extent s_z. So a position
drawn from the footprint is: pick a footprint pixel, follow its camera ray to the
plane z = s_z, and add a normal jitter with the object's horizontal half-extent as
its scale. The proposal is the mixture of those normals (over up to
``MAX_PIXELS`` footprint pixels), each truncated to the floor box the prior lives
on, so its density is exact (:meth:`FootprintProposal.log_density`).

The sampler does not trust it: its first step draws half of its particles from
the prior and half from here, and weighs each draw by prior / (mixture of both)
-- *defensive importance sampling* (Hesterberg 1995), whose weights are at most 2,
so the evidence estimate stays unbiased and the footprint can only make it
cheaper. A shadow pixel's proposal is wrong and its draws simply weigh little.
"""
from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np

MAX_PIXELS = 256
DEFENSIVE_WEIGHT = 0.5      # the prior's share of the first step's proposal


# the fitted threshold is the floor residuals' 99.9th percentile of max over channels |r|: for
# independent normal channels of scale s that percentile is this many s
NOISE_QUANTILE = 3.59


def image_noise(difference: np.ndarray) -> float:
    """The image's own pixel noise from its difference to the empty floor: 1.4826 x the median |difference|
    over every pixel and channel (the MAD; the floor fills most of the image, so the object barely moves it)."""
    return 1.4826 * float(np.median(np.abs(difference)))


def footprint_mask(observed: np.ndarray, empty: np.ndarray, threshold: float) -> np.ndarray:
    """(H, W) pixels where the observed image differs from the empty-floor render by more than ``threshold``
    in some channel.

    An image noisier than the floor the threshold was fitted on (its own noise s, :func:`image_noise`,
    would cross the threshold in more than 0.1% of floor pixels) would be all footprint. Its
    difference is first averaged over k x k pixels, k the least width that brings independent noise
    back under the threshold, and a pixel is footprint where that average exceeds the threshold or,
    near the border where fewer pixels n are averaged, the noise's own 3.59 s / sqrt(n): the
    footprint of a noisy image, e.g. a simulation-based-calibration draw at the likelihood's
    effective scale. None of the benchmarks' real images is that noisy (their 3.59 s is 0.6-0.8 of
    the threshold), so for them this is the plain per-pixel test."""
    from scipy import ndimage

    difference = np.asarray(observed, np.float32) - np.asarray(empty, np.float32)
    noise = image_noise(difference)
    width = int(np.ceil(NOISE_QUANTILE * noise / threshold))
    if width <= 1:
        return np.max(np.abs(difference), axis=-1) > threshold
    box = (width, width)
    count = width * width * ndimage.uniform_filter(np.ones(difference.shape[:2]), box, mode="constant")
    sums = width * width * ndimage.uniform_filter(difference, box + (1,), mode="constant")
    limit = np.maximum(threshold, NOISE_QUANTILE * noise / np.sqrt(np.maximum(count, 1.0)))
    return np.max(np.abs(sums), axis=-1) / count > limit


@dataclass(frozen=True)
class FootprintProposal:
    """Positions proposed from footprint pixels' camera rays (see the module docstring)."""

    origin: np.ndarray        # (3,) camera centre
    directions: np.ndarray    # (K, 3) unit rays of the chosen footprint pixels
    bound: float              # the floor box [-bound, bound]^2 of the prior's positions

    @classmethod
    def of(cls, mask: np.ndarray, origin: np.ndarray, directions: np.ndarray, bound: float,
           rng: np.random.Generator) -> "FootprintProposal | None":
        """From a footprint mask (H, W) and the camera's per-pixel rays (H*W, 3); None for an empty footprint
        or one whose rays never reach the floor's height (a camera looking up)."""
        rays = np.asarray(directions, np.float64)[np.asarray(mask).reshape(-1)]
        rays = rays[rays[:, 2] < -1e-6]
        if len(rays) == 0:
            return None
        if len(rays) > MAX_PIXELS:
            rays = rays[rng.choice(len(rays), MAX_PIXELS, replace=False)]
        return cls(np.asarray(origin, np.float64), rays, float(bound))

    def centres(self, height: np.ndarray) -> np.ndarray:
        """(n, K, 2) where each ray meets the plane z = height (n,)."""
        t = (np.asarray(height, np.float64)[:, None] - self.origin[2]) / self.directions[None, :, 2]
        return self.origin[None, None, :2] + t[..., None] * self.directions[None, :, :2]

    @staticmethod
    def jitter(scale: np.ndarray) -> np.ndarray:
        """(n,) the jitter's sd: the mean horizontal half-extent."""
        return np.mean(np.asarray(scale, np.float64)[:, :2], axis=1)

    def sample(self, rng: np.random.Generator, scale: np.ndarray) -> np.ndarray:
        """(n, 2) positions for objects of half-extents ``scale`` (n, 3), inside the floor box."""
        from scipy.stats import truncnorm

        n = len(scale)
        centre = self.centres(scale[:, 2])[np.arange(n), rng.integers(len(self.directions), size=n)]
        sd = self.jitter(scale)[:, None]
        low, high = (-self.bound - centre) / sd, (self.bound - centre) / sd
        return truncnorm.rvs(low, high, loc=centre, scale=sd, random_state=rng)

    def log_density(self, shift: np.ndarray, scale: np.ndarray) -> np.ndarray:
        """(n,) log q(shift | scale) of the truncated normal mixture: one compiled JAX function
        (:func:`_mixture_log_density`) over every draw and ray, on the device JAX runs on (the rays
        padded to ``MAX_PIXELS``, so every image shares one compilation)."""
        import jax.numpy as jnp

        count = len(self.directions)
        rays = np.zeros((MAX_PIXELS, 3))
        rays[:, 2] = -1.0                                          # padding: never used (masked)
        rays[:count] = self.directions
        valid = np.arange(MAX_PIXELS) < count
        out = _mixture_log_density()(jnp.asarray(shift, jnp.float32), jnp.asarray(scale, jnp.float32),
                                     jnp.asarray(self.origin, jnp.float32), jnp.asarray(rays, jnp.float32),
                                     jnp.asarray(valid), jnp.float32(self.bound))
        return np.asarray(out, np.float64)


@functools.lru_cache(maxsize=None)
def _mixture_log_density():
    """The compiled density of :meth:`FootprintProposal.log_density` (built on first use): per draw,
    log (1/K) sum_k prod_axis N(shift; centre_k, sd) / mass of the floor box under it, over the valid
    rays. The box's mass log(Phi(high) - Phi(low)) is taken on the side of 0 where both tails are
    small, so a box far from a component's centre still gets its tiny mass, not 0."""
    import jax
    import jax.numpy as jnp
    from jax.scipy.special import log_ndtr, logsumexp

    @jax.jit
    def density(shift, scale, origin, rays, valid, bound):
        t = (scale[:, 2:3] - origin[2]) / rays[None, :, 2]                   # (n, K)
        centre = origin[None, None, :2] + t[..., None] * rays[None, :, :2]    # (n, K, 2)
        sd = jnp.mean(scale[:, :2], axis=1)[:, None, None]
        z = (shift[:, None, :] - centre) / sd
        low, high = (-bound - centre) / sd, (bound - centre) / sd
        upper = low > 0                      # both in the upper tail: Phi(-low) - Phi(-high)
        a = jnp.where(upper, log_ndtr(-low), log_ndtr(high))
        b = jnp.where(upper, log_ndtr(-high), log_ndtr(low))
        mass = a + jnp.log1p(-jnp.exp(jnp.minimum(b - a, -1e-30)))
        per_axis = -0.5 * z ** 2 - 0.5 * jnp.log(2 * jnp.pi) - jnp.log(sd) - mass
        terms = jnp.where(valid[None, :], per_axis.sum(axis=-1), -jnp.inf)
        return logsumexp(terms, axis=1) - jnp.log(jnp.sum(valid))

    return density


def shift_log_prior(prior, shift: np.ndarray) -> np.ndarray:
    """(n,) the prior's log density of positions (n, 2): a normal truncated to the floor box, per axis."""
    from scipy.stats import truncnorm

    c = prior.config
    mean = np.asarray(c.shift_mean)
    a, b = (-c.shift_bound - mean) / c.shift_sd, (c.shift_bound - mean) / c.shift_sd
    return np.sum(truncnorm.logpdf(shift, a, b, loc=mean, scale=c.shift_sd), axis=-1)
