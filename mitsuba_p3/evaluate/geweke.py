"""Getting it right: do the SMC's moves leave the posterior invariant? (Geweke 2004)

Simulation-based calibration (:mod:`.sbc`) tests the whole sampler: a failure there can be a
move that targets the wrong distribution, or moves that are right but a search that does not
find the posterior's mass. Geweke's *successive-conditional simulator* tells the two apart. It
alternates

    y_t ~ p(y | z_t)               (render z_t and add the likelihood's noise)
    z_{t+1} ~ K(z_t, . ; y_t)      (one move of the sampler at lambda = 1)

from z_0 drawn from the prior. Under the shading fields' form (:mod:`mitsuba_p3.fit.fields`) y_t is the
render plus a draw of the fields on its object, shadow and floor (loaded on z_t's own colour where they
are tinted) plus white noise: the density the sampler scores, so the check covers the fields' terms of
the material update too. If K leaves each posterior p(z | y) invariant, the pair (z_t, y_t)
keeps the joint p(z) p(y | z), so every z_t is again a prior draw, however many moves are made,
whether or not K mixes well. A move with a wrong Hastings term, a conditional drawn from the wrong
distribution, or a density that disagrees with the simulator drifts z_t away from the prior; the
drift grows with the number of moves. Mixing does not matter, so this test cannot be passed by a
broad search, and a poor search cannot fail it. Its power is for errors that move z on the prior's
scale (a simulator that disagrees with the renders, a conditional drawn from the wrong place): an
error of the posterior's own width (moves at the wrong temperature) is pulled back by the prior at
every step and stays within a fraction of the prior's spread.

Each of many independent chains runs ``steps`` successive-conditional steps; their final states
are compared with fresh prior draws of the same hypothesis coordinate by coordinate (two-sample
Kolmogorov-Smirnov, the coordinates :data:`~.sbc.CHECKED` that SBC ranks, plus the yaw and
the material weights). The moves are the SMC's own jitted kernels (:mod:`mitsuba_p3.infer.smc_moves`):
the random walk with the symmetry (and ridge) moves, and the material Metropolis-within-Gibbs
update, each applied to one chain per row with the chain's own image.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .sbc import CHECKED, checked_values

GEWEKE_NAMES = CHECKED + ("theta", "ambient", "diffuse", "specular", "shininess")


def natural(prior, z: np.ndarray) -> np.ndarray:
    """(n, len(GEWEKE_NAMES)) the compared coordinates of points z (n, 15)."""
    import jax.numpy as jnp

    x = {k: np.asarray(v) for k, v in prior.constrain(jnp.asarray(z)).items()}
    rest = np.stack([x[k] for k in GEWEKE_NAMES[len(CHECKED):]], axis=-1)
    return np.concatenate([checked_values(x), rest], axis=-1)


@dataclass(frozen=True)
class GewekeResult:
    """KS p-values per coordinate and move set, and the moves' mean acceptance."""
    names: tuple
    pvalues: dict            # move set -> (len(names),) two-sample KS p-values
    acceptance: dict         # move set -> mean acceptance of its moves over the run
    chains: int
    steps: int

    def summary(self) -> dict:
        return {"chains": self.chains, "steps": self.steps, "names": list(self.names),
                "pvalues": {k: [float(p) for p in v] for k, v in self.pvalues.items()},
                "min_pvalue": {k: float(np.min(v)) for k, v in self.pvalues.items()},
                "acceptance": {k: float(v) for k, v in self.acceptance.items()}}


def successive_conditional(core, hypothesis: int, moves: str, chains: int, steps: int, seed: int = 0,
                           walk_scale: float = 0.05, tempering: float = 1.0) -> tuple[np.ndarray, float]:
    """Run ``chains`` successive-conditional chains of one hypothesis (a row of
    :func:`~mitsuba_p3.infer.hypotheses.hypotheses_of` without kinds) for ``steps`` steps with the SMC
    move set ``moves`` (``walk``: random walk + symmetry + ridge; ``material``: the material update;
    ``both``). The walk's covariance is ``walk_scale`` times the prior draws' own (fixed: an adaptive
    covariance would be another test). The moves target p(z) p(y | z)^``tempering``: anything but 1 is a
    deliberately wrong kernel (whose error is of the posterior's width, which this check barely sees:
    the module docstring); ``jump``: the material update that starts with the material kind's jump.
    Returns the chains' final points (chains, 15) and the mean acceptance (for ``jump``, the jump's)."""
    import jax
    import jax.numpy as jnp

    from ..infer.hypotheses import hypotheses_of, initial_particles
    from ..infer.move_scales import WALK_MASK, covariance_factors
    from ..infer.smc_moves import kernels

    rng = np.random.default_rng(seed)
    space = hypotheses_of(core.prior, False)
    start = initial_particles(core.prior, rng, chains, space)[hypothesis]           # (chains, 15)
    k = kernels(core, False, 1, jump=moves == "jump")
    tril = jnp.asarray(walk_scale * covariance_factors(start[None], WALK_MASK), jnp.float32)   # (1, d, d)
    index = jnp.asarray([hypothesis], jnp.int32)
    lam = jnp.full(1, tempering, jnp.float32)
    centre = jnp.zeros(1, jnp.float32)        # the walk's symmetry chart: the copy within 45 degrees of yaw 0
    sigma = core.config.sigma / np.sqrt(core.config.power)
    extra = {"empty": jnp.asarray(core.empty)} if core.config.fields is not None else {}

    def one(key, z, image):
        """One chain's moves given its image: rows of one particle."""
        observation = {"image": image, **extra}
        state = k.score(z[None, None], index, observation)
        particles = (z[None, None], state[0], state[1])
        rates = []
        k_walk, k_material = jax.random.split(key)
        if moves in ("walk", "both"):
            particles, accepted = k.walk(k_walk, particles, index, lam, tril, centre, observation)
            rates.append(accepted[0])
        if moves in ("material", "both", "jump"):
            particles, accepted, _, jumped = k.material(k_material, particles, index, lam, observation)
            rates.append(jumped[0] if moves == "jump" else accepted[0])
        return particles[0][0, 0], jnp.mean(jnp.stack(rates))

    step = jax.jit(jax.vmap(one))
    render = jax.jit(jax.vmap(core.render))
    fields = jax.jit(jax.vmap(lambda key, z, image: field_draw(core, key, z, image)))
    z = jnp.asarray(start)
    key = jax.random.PRNGKey(seed)
    accepted = []
    for _ in range(steps):
        key, k_noise, k_move, k_fields = jax.random.split(key, 4)
        images = render(z)
        if extra:
            images = images + fields(jax.random.split(k_fields, chains), z, images)
        images = images + sigma * jax.random.normal(k_noise, images.shape)
        z, rate = step(jax.random.split(k_move, chains), z, images)
        accepted.append(float(jnp.mean(rate)))
    return np.asarray(z), float(np.mean(accepted))


def field_draw(core, key, z, render):
    """One draw of the shading fields (h, w, 3) on the whole image ``render`` of position z: on its
    object's pixels, the floor its shadow changes and the rest of the floor, w ~ N(0, tau^2) per column
    (:func:`mitsuba_p3.fit.fields.sample_fields`, in JAX), loaded on z's colour where the fields are tinted."""
    import jax
    import jax.numpy as jnp

    from ..fit.fields import per_region
    from ..infer.likelihood import fields_form, fields_masks, fields_regions

    height, width = render.shape[:2]
    masks = fields_masks(render, core.objects(z, {"image": render}), jnp.asarray(core.empty), fields_regions(core.config))
    variances, basis, loading = fields_form(core.config, height, width, colours=core.params(z)["colour"], xp=jnp)
    loading = per_region(jnp.asarray(loading, jnp.float32), masks.shape[0], jnp)
    weights = jax.random.normal(key, np.shape(variances)) * jnp.sqrt(jnp.asarray(variances, jnp.float32))
    return jnp.einsum("rhw,hwm,rjmc,rj->hwc", masks.astype(jnp.float32), jnp.asarray(basis, jnp.float32), loading,
                      weights)


def geweke_check(core, hypothesis: int = 0, move_sets=("walk", "material"), chains: int = 400, steps: int = 10,
                 seed: int = 0, walk_scale: float = 0.05, tempering: float = 1.0) -> GewekeResult:
    """The successive-conditional test of each move set (module docstring): KS p-values of the chains'
    final states against fresh prior draws of the same hypothesis (``tempering``: see
    :func:`successive_conditional`)."""
    from scipy.stats import ks_2samp

    from ..infer.hypotheses import hypotheses_of, initial_particles

    # the reference: 4 x as many fresh prior draws, from a stream of their own
    fresh = initial_particles(core.prior, np.random.default_rng([seed, 1]), 4 * chains,
                              hypotheses_of(core.prior, False))
    reference = natural(core.prior, fresh[hypothesis])
    pvalues, acceptance = {}, {}
    for moves in move_sets:
        end, rate = successive_conditional(core, hypothesis, moves, chains, steps, seed, walk_scale,
                                           tempering)
        values = natural(core.prior, end)
        pvalues[moves] = np.array([ks_2samp(values[:, i], reference[:, i]).pvalue for i in range(values.shape[1])])
        acceptance[moves] = rate
    return GewekeResult(GEWEKE_NAMES, pvalues, acceptance, chains, steps)
