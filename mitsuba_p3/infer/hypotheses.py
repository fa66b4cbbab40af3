"""The discrete hypotheses an SMC run weighs, and where its first particles come from.

A hypothesis h is a shape class (sphere, cube, cylinder), or with ``kinds`` a shape class
times a material kind (matte, shiny). Within h the class logits are fixed
(:data:`CLASS_LOGITS`) and the rest of the model's prior is h's prior, p(z | h)
(:func:`hypothesis_log_prior`). A run of h starts from draws of p(z | h)
(:func:`initial_particles`); half of them can instead be placed from the image's
footprint, the connected region where the image differs from the empty floor
(:func:`footprint_start`), with log importance weights that keep the first step's
evidence estimate unbiased.
"""
from __future__ import annotations

from typing import NamedTuple

import numpy as np

from ..shapes import SHAPES
from ..space import HYPOTHESES, MATERIAL_KINDS, SLICES

# class logits (z_kappa) that put a point firmly in each shape class: softmax([z1, z2, 0])
CLASS_LOGITS = np.array([[8.0, 0.0], [0.0, 8.0], [-8.0, -8.0]], np.float32)


class Hypotheses(NamedTuple):
    """The discrete hypotheses an SMC run weighs: names, shape class index, log p(h), and the specular
    weight's prior given h in z (mean, sd of one Gaussian component; NaN: the model's whole mixture)."""
    names: tuple
    classes: np.ndarray
    log_prior: np.ndarray
    specular_mean: np.ndarray
    specular_sd: np.ndarray


def hypotheses_of(prior, kinds: bool) -> Hypotheses:
    """Shape classes (``kinds`` False: the material kind is left to the material moves, and its
    posterior is the particles' share on each side of the specular threshold), or shape x material
    kind (True: the matte and shiny components of the specular prior, each a hypothesis)."""
    log_class = np.log(np.asarray(prior.config.class_probabilities, np.float64))
    if not kinds:
        nan = np.full(len(SHAPES), np.nan)
        return Hypotheses(tuple(SHAPES), np.arange(len(SHAPES)), log_class, nan, nan)
    g = prior.gmms["specular"]
    order = np.argsort(g.means[:, 0])                  # matte: the lower component
    components = list(order) if len(order) == len(MATERIAL_KINDS) else [order[0]] * len(MATERIAL_KINDS)
    weights = np.array([g.weights[c] if len(order) > 1 else 0.5 for c in components])
    log_p = np.array([log_class[s] + np.log(weights[k]) for s in range(len(SHAPES)) for k in range(len(components))])
    means = np.array([(g.means[c, 0] - g.mean[0]) / g.std[0] for _ in SHAPES for c in components])
    sds = np.array([np.sqrt(g.variances[c, 0]) / g.std[0] for _ in SHAPES for c in components])
    classes = np.repeat(np.arange(len(SHAPES)), len(MATERIAL_KINDS))
    return Hypotheses(HYPOTHESES, classes, log_p, means, sds)


def initial_particles(prior, rng: np.random.Generator, particles: int, hypotheses: Hypotheses) -> np.ndarray:
    """(H, N, 15) draws from the prior given each hypothesis."""
    count = len(hypotheses.names)
    z = prior.sample(rng, count * particles).reshape(count, particles, -1).astype(np.float32)
    for h in range(count):
        z[h, :, SLICES["kappa"]] = CLASS_LOGITS[hypotheses.classes[h]]
        if np.isfinite(hypotheses.specular_mean[h]):
            z[h, :, SLICES["specular"].start] = (hypotheses.specular_mean[h]
                                                 + hypotheses.specular_sd[h] * rng.standard_normal(particles))
    return z


def hypothesis_log_prior(prior, hypotheses: Hypotheses):
    """log p(z | h) for one position and hypothesis index (JAX): the model's prior without the class
    term, the specular weight's density that of h's component when h names one."""
    import jax.numpy as jnp
    from jax.scipy.stats import norm

    spec = SLICES["specular"].start
    means = jnp.asarray(np.nan_to_num(hypotheses.specular_mean))
    sds = jnp.asarray(np.nan_to_num(hypotheses.specular_sd, nan=1.0))
    own = jnp.asarray(np.isfinite(hypotheses.specular_mean))

    def log_prior(z, h):
        parts = prior.log_prob_parts(z)
        rest = sum(v for k, v in parts.items() if k not in ("kappa", "specular"))
        return rest + jnp.where(own[h], norm.logpdf(z[spec], means[h], sds[h]), parts["specular"])

    return log_prior



def footprint_start(core, image: np.ndarray, draws: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Place every other first-step draw (H, M, 15, in place) from the image's footprint
    (:mod:`mitsuba_p3.infer.footprint`) and return each draw's log importance weight (H, M),
    log prior - log (defensive mixture), for the position; zeros when there is no footprint."""
    from .footprint import DEFENSIVE_WEIGHT, FootprintProposal, footprint_mask, shift_log_prior

    threshold = core.footprint_threshold
    if threshold is None:
        return np.zeros(draws.shape[:2])
    origin, directions = core.camera_rays
    mask = footprint_mask(image, core.empty, threshold)
    bound = core.prior.config.shift_bound
    proposal = FootprintProposal.of(mask, origin, directions, bound, rng)
    if proposal is None:
        return np.zeros(draws.shape[:2])
    flat = draws.reshape(-1, draws.shape[-1])
    scale = np.exp(flat[:, SLICES["scale"]].astype(np.float64))
    placed = np.arange(len(flat)) % 2 == 1
    shift = np.asarray(core.prior.constrain(flat)["shift"], np.float64)
    shift[placed] = proposal.sample(rng, scale[placed])
    u = np.clip((shift + bound) / (2 * bound), 1e-7, 1 - 1e-7)
    flat[:, SLICES["shift"]] = np.log(u) - np.log1p(-u)
    log_p = shift_log_prior(core.prior, shift)
    log_q = np.logaddexp(np.log(DEFENSIVE_WEIGHT) + log_p,
                         np.log1p(-DEFENSIVE_WEIGHT) + proposal.log_density(shift, scale))
    draws[:] = flat.reshape(draws.shape)
    return (log_p - log_q).reshape(draws.shape[:2])
