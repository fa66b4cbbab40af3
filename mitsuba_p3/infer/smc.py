"""Tempered sequential Monte Carlo over the discrete hypotheses: the shape classes.

A random walk over a relaxed one-hot class cannot cross between shape modes once
the likelihood is sharp. Here each hypothesis h (sphere, cube or cylinder) is a
posterior of its own, over the continuous parameters, and its *evidence*
Z_h = p(I | h) decides between them:

    p(h | I) = p(h) Z_h / sum_h' p(h') Z_h',    p(h) the prior's class probability.

Each hypothesis runs a tempered SMC (Del Moral et al. 2006; blackjax's
``adaptive_tempered_smc`` is the same algorithm): N particles move through the
targets p(z | h) p(I | z)^lambda as lambda rises from 0 to 1. Each step chooses
the increment of lambda by bisection so that the incremental weights keep an
effective sample size of ``target_ess`` N, adds log mean exp(dlambda log p(I | z))
to log Z_h, resamples (systematic), and moves every particle with ``mcmc_steps``
sweeps of the moves the MH sampler uses: a Gaussian random walk over position,
yaw and size (covariance 2.38^2 / d times the particles' own, scaled towards 25%
acceptance) with the symmetry move after it, and every ``material_every`` sweeps
the material Metropolis-within-Gibbs update (one render of the material bases,
the costliest move), all at the current temperature. All particles of all
hypotheses are scored in one batched render per move.

**The first step starts from the image.** It draws ``oversample`` x N scenes per
hypothesis, half from the prior and half with their position taken from the
image's footprint (:mod:`mitsuba_p3.infer.footprint`), weighs each by
prior / (the mixture of both) times its likelihood^lambda_1, and keeps N: an
importance-sampling step whose evidence estimate is unbiased, so the footprint
makes the search cheaper without changing what is estimated.

**Material kind.** By default the matte/shiny decision is left inside each shape's
run: the specular weight keeps the prior's two-component mixture, the material
update proposes from both components, and p(shiny | h, I) is the particles' share
above the prior's threshold (``shiny`` in the statistics). ``kinds=True`` makes
shape x material kind six hypotheses of their own instead (twice the cost; their
specular priors are the mixture's components).

**Islands.** ``islands=k`` runs k independent SMCs per hypothesis, all in the same
batched renders (each island a row of its own). Each gives an unbiased estimate
of Z_h, so their mean is one, with k times less variance; a failed island (one
that missed the object's pose) underestimates Z_h and weighs little. The draws
come from each island in proportion to its estimate.

Within a hypothesis the class logits are fixed (they play no role); the rest of
the prior is the model's. The result is a :class:`~mitsuba_p3.infer.mcmc.SamplerRun`
of draws from the mixture over hypotheses, with each hypothesis's log evidence,
weight and shiny share in its statistics.
"""
from __future__ import annotations

import functools
import time
from dataclasses import asdict, dataclass
from typing import Callable, NamedTuple

import numpy as np

from ..shapes import SHAPES
from ..space import DIMENSION, HYPOTHESES, MATERIAL_KINDS, SLICES
from .mcmc import SamplerRun

# class logits (z_kappa) that put a point firmly in each shape class: softmax([z1, z2, 0])
CLASS_LOGITS = np.array([[8.0, 0.0], [0.0, 8.0], [-8.0, -8.0]], np.float32)


@dataclass(frozen=True)
class SMCConfig:
    particles: int = 32            # per hypothesis
    oversample: int = 8            # prior draws per particle at the start (the first reweighting picks N of them)
    mcmc_steps: int = 3            # random-walk sweeps per temperature
    material_every: int = 3        # a material update after every k-th sweep (and the last)
    final_steps: int = 6           # extra sweeps at lambda = 1, to spread the resampled particles again
    footprint: bool = True         # half of the first step's draws placed from the image's footprint
    kinds: bool = False            # material kinds as hypotheses of their own (else within each shape)
    islands: int = 1               # independent SMC runs per hypothesis, their evidence pooled
    target_ess: float = 0.5        # of the incremental weights, as a share of the particles
    max_temperatures: int = 100    # a run that needs more jumps to lambda = 1 (statistics: 'forced')
    draws: int = 400               # posterior draws returned (resampled from the mixture)
    seed: int = 0

    def __post_init__(self):
        from ..errors import ConfigError, check_counts

        check_counts(self, {"particles": 4, "oversample": 1, "mcmc_steps": 1, "material_every": 1, "final_steps": 0,
                            "islands": 1, "max_temperatures": 1, "draws": 4, "seed": 0}, "smc ")
        if not 0.0 < self.target_ess < 1.0:
            raise ConfigError(f"smc target-ess must lie in (0, 1); got {self.target_ess}")


class SMCState(NamedTuple):
    """Particles of every hypothesis: positions (H, N, d), log likelihoods and log priors (H, N)."""
    position: np.ndarray
    loglikelihood: np.ndarray
    logprior: np.ndarray


class Hypotheses(NamedTuple):
    """The discrete hypotheses an SMC run weighs: names, shape class index, log p(h), and the specular
    weight's prior given h in z (mean, sd of one Gaussian component; NaN: the model's whole mixture)."""
    names: tuple
    classes: np.ndarray
    log_prior: np.ndarray
    specular_mean: np.ndarray
    specular_sd: np.ndarray


def hypotheses_of(prior, kinds: bool, islands: int = 1) -> Hypotheses:
    """Shape classes (``kinds`` False: the material kind is left to the material moves, and its
    posterior is the particles' share on each side of the specular threshold), or shape x material
    kind (True: the matte and shiny components of the specular prior, each a hypothesis); each
    repeated ``islands`` times, one row per independent run (island i of hypothesis h is row
    i * H + h)."""
    if islands > 1:
        one = hypotheses_of(prior, kinds)
        return Hypotheses(one.names * islands, *(np.tile(a, islands) for a in one[1:]))
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


def next_increment(loglikelihood: np.ndarray, remaining: float, target_ess: float, offset=0.0) -> float:
    """The largest tempering increment <= ``remaining`` whose incremental weights
    ``step * loglikelihood + offset`` keep ESS >= target."""
    def ess(step):
        w = step * (loglikelihood - loglikelihood.max()) + offset
        w = np.exp(w - w.max())
        return w.sum() ** 2 / np.sum(w ** 2) / len(w)

    if ess(remaining) >= target_ess:
        return remaining
    low, high = 0.0, remaining
    for _ in range(40):
        middle = 0.5 * (low + high)
        low, high = (middle, high) if ess(middle) >= target_ess else (low, middle)
    return max(low, 1e-6)


def systematic_resample(rng: np.random.Generator, log_weights: np.ndarray, count: int | None = None) -> np.ndarray:
    """``count`` (default: as many as weights) indices drawn in proportion to the weights, systematically."""
    count = len(log_weights) if count is None else count
    w = np.exp(log_weights - log_weights.max())
    cumulative = np.cumsum(w / w.sum())
    positions = (rng.uniform() + np.arange(count)) / count
    return np.minimum(np.searchsorted(cumulative, positions), len(w) - 1)


def footprint_start(core, observation, draws: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Place every other first-step draw (H, M, 15, in place) from the image's footprint
    (:mod:`mitsuba_p3.infer.footprint`) and return each draw's log importance weight (H, M),
    log prior - log (defensive mixture), for the position; zeros when there is no footprint."""
    from .footprint import DEFENSIVE_WEIGHT, FootprintProposal, footprint_mask, shift_log_prior

    threshold = core.footprint_threshold
    if threshold is None:
        return np.zeros(draws.shape[:2])
    origin, directions = core.camera_rays
    mask = footprint_mask(observation["image"], core.empty, threshold)
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


@functools.lru_cache(maxsize=4)
def _kernels(core, walk_mask: tuple, kinds: bool, islands: int):
    """Jitted (score, walk, material) for one :class:`PosteriorCore`: scores of all particles, and the two
    moves of all particles at per-hypothesis temperatures."""
    import jax
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import RWState

    space = hypotheses_of(core.prior, kinds, islands)
    log_prior = hypothesis_log_prior(core.prior, space)
    mask = jnp.asarray(walk_mask, jnp.float32)
    hypotheses = len(space.names)

    def loglik_all(z, observation):                               # (H, N, d) -> (H, N)
        flat = z.reshape(-1, z.shape[-1])
        return jax.vmap(lambda p: core.log_likelihood(p, observation))(flat).reshape(z.shape[:2])

    def logprior_all(z):
        h = jnp.broadcast_to(jnp.arange(hypotheses)[:, None], z.shape[:2])
        return jax.vmap(jax.vmap(log_prior))(z, h)

    @jax.jit
    def score(z, observation):
        return loglik_all(z, observation), logprior_all(z)

    @jax.jit
    def walk(key, state, tempering, tril, observation):
        """The random walk, then the symmetry move; returns (state, walk acceptance (H,))."""
        k_walk, k_accept, k_symmetry = jax.random.split(key, 3)
        z, loglik, logprior = state
        noise = jax.random.normal(k_walk, z.shape) * mask
        proposed = z + jnp.einsum("hij,hnj->hni", tril, noise)
        new_loglik, new_logprior = loglik_all(proposed, observation), logprior_all(proposed)
        log_ratio = new_logprior + tempering[:, None] * new_loglik - logprior - tempering[:, None] * loglik
        accept = jnp.log(jax.random.uniform(k_accept, loglik.shape)) < log_ratio
        z = jnp.where(accept[..., None], proposed, z)
        loglik, logprior = jnp.where(accept, new_loglik, loglik), jnp.where(accept, new_logprior, logprior)
        # symmetry: no render; the tempered density changes only through the yaw prior
        flat = RWState(z.reshape(-1, z.shape[-1]), logprior.reshape(-1))
        turned = jax.vmap(core.symmetry_move)(jax.random.split(k_symmetry, flat.position.shape[0]), flat)
        return SMCState(turned.position.reshape(z.shape), loglik, turned.logdensity.reshape(logprior.shape)), \
            accept.mean(axis=1)

    @jax.jit
    def material(key, state, tempering, observation):
        """The material Metropolis-within-Gibbs update at each hypothesis's temperature (one render of
        the material bases per particle, then one render to score the result)."""
        z, loglik, logprior = state
        h = jnp.repeat(jnp.arange(hypotheses), z.shape[1])
        lam = jnp.repeat(tempering, z.shape[1])

        def one(key, position, logprior_value, loglik_value, index, lam_value):
            state = RWState(position, logprior_value + lam_value * loglik_value)
            new, _ = core.material_move(key, state, observation, lam_value, lambda p: log_prior(p, index))
            return new.position

        keys = jax.random.split(key, h.shape[0])
        moved = jax.vmap(one)(keys, z.reshape(-1, z.shape[-1]), logprior.reshape(-1), loglik.reshape(-1),
                              h, lam).reshape(z.shape)
        return SMCState(moved, loglik_all(moved, observation), logprior_all(moved))

    return score, walk, material


def sample_smc(core, observation, config: SMCConfig | None = None,
               progress: Callable[[str, int, int], None] | None = None) -> SamplerRun:
    """Tempered SMC of every hypothesis of one image (see the module docstring)."""
    import jax
    import jax.numpy as jnp

    config = config or SMCConfig()
    start = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    key = jax.random.PRNGKey(config.seed)
    mask = np.ones(DIMENSION, np.float32)
    for name in ("kappa", "colour", "ambient", "diffuse", "specular"):
        mask[SLICES[name]] = 0.0          # fixed by the hypothesis, or the material update's business
    score, walk, material = _kernels(core, tuple(mask.tolist()), config.kinds, config.islands)
    space = hypotheses_of(core.prior, config.kinds, config.islands)
    hypotheses, n = len(space.names), config.particles
    # the first reweighting starts from oversample x N prior draws and keeps N: a valid SMC step
    # (its evidence increment averages over all draws) that finds the object with few particles
    draws = initial_particles(core.prior, rng, n * config.oversample, space)
    offset = footprint_start(core, observation, draws, rng) if config.footprint else np.zeros(draws.shape[:2])
    all_loglik, all_logprior = (np.asarray(a) for a in score(jnp.asarray(draws), observation))
    z = np.empty((hypotheses, n) + draws.shape[2:], np.float32)
    loglik, logprior = np.empty((hypotheses, n), np.float32), np.empty((hypotheses, n), np.float32)
    tempering, log_evidence = np.zeros(hypotheses), np.zeros(hypotheses)
    for h in range(hypotheses):
        ll = np.where(np.isfinite(all_loglik[h]), all_loglik[h], -1e30)
        step = next_increment(ll, 1.0, config.target_ess / config.oversample, offset[h])
        log_evidence[h] = np.logaddexp.reduce(step * ll + offset[h]) - np.log(len(ll))
        tempering[h] = step
        index = systematic_resample(rng, step * ll + offset[h], n)
        z[h], loglik[h], logprior[h] = draws[h][index], all_loglik[h][index], all_logprior[h][index]
    scale = np.full(hypotheses, 1.0)
    acceptance_history, steps = [], 0
    while steps < config.max_temperatures:
        steps += 1
        for h in range(hypotheses):
            if tempering[h] >= 1.0 or steps == 1:   # the first step's reweighting is done above
                continue
            ll = np.where(np.isfinite(loglik[h]), loglik[h], -1e30)
            step = next_increment(ll, 1.0 - tempering[h], config.target_ess)
            if steps == config.max_temperatures:
                step = 1.0 - tempering[h]
            log_w = step * ll
            log_evidence[h] += np.logaddexp.reduce(log_w) - np.log(len(log_w))
            tempering[h] = min(1.0, tempering[h] + step)
            index = systematic_resample(rng, log_w)
            z[h], loglik[h], logprior[h] = z[h][index], loglik[h][index], logprior[h][index]
        # walk covariance per hypothesis from its particles (moved dimensions only)
        moved = mask > 0
        tril = np.zeros((hypotheses, DIMENSION, DIMENSION), np.float32)
        for h in range(hypotheses):
            cov = np.cov(z[h][:, moved], rowvar=False) + 1e-6 * np.eye(moved.sum())
            tril[h][np.ix_(moved, moved)] = np.linalg.cholesky(cov) * 2.38 / np.sqrt(moved.sum()) * scale[h]
        state = SMCState(jnp.asarray(z), jnp.asarray(loglik), jnp.asarray(logprior))
        rates = []
        lam = jnp.asarray(tempering, jnp.float32)
        sweeps = config.mcmc_steps + (config.final_steps if np.all(tempering >= 1.0) else 0)
        for i in range(sweeps):
            key, k_walk, k_material = jax.random.split(key, 3)
            state, accepted = walk(k_walk, state, lam, jnp.asarray(tril), observation)
            rates.append(np.asarray(accepted))
            if (i + 1) % config.material_every == 0 or i == sweeps - 1:
                state = material(k_material, state, lam, observation)
        z, loglik, logprior = (np.array(a) for a in state)
        rate = np.mean(rates, axis=0)
        scale *= np.clip(np.exp(2.0 * (rate - 0.25)), 0.5, 2.0)   # towards 25% walk acceptance
        acceptance_history.append(rate.tolist())
        if progress:
            progress("smc", int(100 * tempering.min()), 100)
        if np.all(tempering >= 1.0):
            break
    # islands: the mean of their unbiased evidence estimates is one; a row's share of its hypothesis is
    # its own estimate's share of the sum
    base = len(space.names) // config.islands
    rows = log_evidence.reshape(config.islands, base)
    pooled = np.logaddexp.reduce(rows, axis=0) - np.log(config.islands)
    log_posterior = space.log_prior[:base] + pooled
    weights = np.exp(log_posterior - np.logaddexp.reduce(log_posterior))
    row_weights = (np.exp(rows - np.logaddexp.reduce(rows, axis=0)) * weights).reshape(-1)
    # draws: rows by their posterior weight, particles uniformly (equal weights after resampling)
    chains = 4
    per_chain = max(1, config.draws // chains)
    chosen_h = rng.choice(hypotheses, size=chains * per_chain, p=row_weights / row_weights.sum())
    chosen_n = rng.integers(config.particles, size=chains * per_chain)
    positions = z[chosen_h, chosen_n].reshape(chains, per_chain, -1)
    logdensity = (logprior + loglik)[chosen_h, chosen_n].reshape(chains, per_chain)
    shiny = (z[..., SLICES["specular"].start] > core.prior.specular_threshold()).mean(axis=1)    # per row
    shiny = np.sum(shiny.reshape(config.islands, base) * np.exp(rows - np.logaddexp.reduce(rows, axis=0)), axis=0)
    statistics = {"hypotheses": {name: {"log_evidence": float(pooled[h]), "weight": float(weights[h]),
                                        "shiny": float(shiny[h])}
                                 for h, name in enumerate(space.names[:base])},
                  "temperatures": steps, "forced": bool(steps == config.max_temperatures),
                  "walk_acceptance": float(np.mean(acceptance_history[-1])),
                  "seconds": time.perf_counter() - start}
    return SamplerRun(positions.astype(np.float32), logdensity.astype(np.float32),
                      np.ones((chains, per_chain), bool), {}, [{"acceptance": a} for a in acceptance_history],
                      {"sampler": "smc", **asdict(config)}, statistics)
