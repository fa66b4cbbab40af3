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
hypotheses are scored in one batched render per move. A walk sweep costs about a
third of a material update, and the walks are what carry a run to the object's
exact pose and size: on 30 train images of fsclvr at 120x160, five walks per
material update found the true shape for 90% (mean log p(true shape) -0.36)
against 67% (-5.2) with three, in about the same time (``scripts/select_smc.py``;
on the test split the runs took 1.24 times as long as with three).

**The first step starts from the image.** It draws ``oversample`` x N scenes per
hypothesis, half from the prior and half with their position taken from the
image's footprint (:mod:`mitsuba_p3.infer.footprint`), weighs each by
prior / (the mixture of both) times its likelihood^lambda_1, and keeps N: an
importance-sampling step whose evidence estimate is unbiased, so the footprint
makes the search cheaper without changing what is estimated.

**A window around the object.** A render costs in proportion to its pixels, and at
120x160 most of them are empty floor that every hypothesis explains alike. With
``window=(h, w)`` the likelihood scores only an h x w window centred on the largest
connected part of the image's footprint (object and shadow;
:meth:`~mitsuba_p3.infer.model.PosteriorCore.window_for`), and every render of the run
traces only those pixels (:meth:`~mitsuba_p3.render.mitsuba.MitsubaRenderer.window`, or the JAX
tracer's ``render_jax(window=...)``).
Every hypothesis is scored on the same pixels, so their evidences stay comparable; an
image whose footprint does not fit the window is scored whole.

**One object, or nothing?** The hypotheses' evidence, weighed by their prior, is the evidence of
"one object"; the empty floor is a model without parameters, whose evidence is its likelihood on
the same window (:func:`object_evidence`). Their log ratio, ``log_bayes_factor_object``, is
negative when the floor alone explains the image better: ``infer`` then warns instead of naming
an object with confidence.

**Material kind.** By default the matte/shiny decision is left inside each shape's
run: the specular weight keeps the prior's two-component mixture, the material
update proposes from both components, and p(shiny | h, I) is the particles' share
above the prior's threshold (``shiny`` in the statistics). ``kinds=True`` makes
shape x material kind six hypotheses of their own instead (twice the cost; their
specular priors are the mixture's components).

**Along the colour/weight ridge.** The image sees the colour only through c k_a and c k_d,
so (c s, k_a / s, k_d / s) renders the same scene for every s > 0, and the material update
(colour given weights, then weights given colour) crawls along that ridge once the likelihood
is sharp. After every walk, ``ridge`` MH moves propose log s ~ N(0, 0.2^2) and accept with the
prior's ratio times the Jacobian s, without a render
(:meth:`~mitsuba_p3.infer.model.PosteriorCore.ridge_move`). Chosen on train images of fsclvr
(``docs/notebook.md``): with three per walk, the colour's R-hat across four seeds fell from
1.11 to 1.02 (median of six images) and 1-shot accuracy on held-out train classes rose from
93.6 / 87.5 to 95.2 / 91.1 (5-way / 10-way, with the concept spread).

**Islands and rounds.** ``islands=k`` runs k independent SMCs per hypothesis, all in the
same batched renders (each run a row of its own). Each gives an unbiased estimate of Z_h,
so their mean is one, with k times less variance; a failed run (one that missed the
object's pose) underestimates Z_h and weighs little. ``rounds=r`` spends more runs only
where the answer is still open: after each round, if the leading hypothesis does not yet
have posterior weight ``decided``, another round runs ``islands`` more SMCs of the hypotheses
still in contention (weight at least (1 - decided) / H), and their estimates join the pool.
"Yet" is judged against the runs' own disagreement (:func:`decision`): the leader counts as
decided only at its lowest run's estimate against the others' highest, and a hypothesis is in
contention if at its highest it could reach that weight against the others' lowest. A run
that missed the pose estimates tens of nats low (fsclvr's large gray metal cube, seed 0: the
cylinder's runs 49.7 and 76.7, the cube's 42.8 and 47.7, so pooled the cylinder had weight 1.0
and won; a second round's cube run found 139 at its best particle). A clear image costs one
round; an ambiguous one, or one whose runs disagree, up to r. The default is one round: up
to three were better on fsclvr's train images and worse on room's (``docs/notebook.md``),
at 1.5 times the mean cost. The draws come from each run in
proportion to its share of its hypothesis's pooled estimate.

**NP3 from P3's posterior.** NP3's likelihood is P3's colour likelihood times a neural term,
so NP3's run need not start from the prior: :func:`bridge` takes P3's final particles of the
same image (every run, on the window P3 scored) and tempers only the neural term in, each run's
evidence growing from P3's by the mean of the neural term's weights (Z_NP3 = Z_P3 E_P3[p_neural]).
It is the same kind of SMC step as the rest, so the estimate stays unbiased; since the neural
term moves the posterior little on this data, it costs a fraction of a run from the prior.
``bridge=False`` runs NP3 from the prior like P3.

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

from ..fit.noise import SCORING_WINDOW
from ..shapes import SHAPES
from ..space import DIMENSION, HYPOTHESES, MATERIAL_KINDS, SLICES
from .mcmc import SamplerRun

# class logits (z_kappa) that put a point firmly in each shape class: softmax([z1, z2, 0])
CLASS_LOGITS = np.array([[8.0, 0.0], [0.0, 8.0], [-8.0, -8.0]], np.float32)
# what the random walk moves: not the class (fixed by the hypothesis) nor the material (the material update's)
WALK_MASK = np.array([0.0 if any(i in range(DIMENSION)[SLICES[name]]
                                 for name in ("kappa", "colour", "ambient", "diffuse", "specular")) else 1.0
                      for i in range(DIMENSION)], np.float32)


@dataclass(frozen=True)
class SMCConfig:
    particles: int = 64            # per hypothesis and run
    oversample: int = 8            # prior draws per particle at the start (the first reweighting picks N of them)
    mcmc_steps: int = 5            # random-walk sweeps per temperature
    material_every: int = 5        # a material update after every k-th sweep (and the last)
    final_steps: int = 6           # extra sweeps at lambda = 1, to spread the resampled particles again
    footprint: bool = True         # half of the first step's draws placed from the image's footprint
    kinds: bool = False            # material kinds as hypotheses of their own (else within each shape)
    ridge: int = 3                 # ridge moves (colour x s, weights / s; no render) after every walk
    islands: int = 2               # independent SMC runs per hypothesis and round, their evidence pooled
    rounds: int = 1                # rounds of runs; a round after the first runs only the contenders
    decided: float = 0.99          # no further round once the leader has this weight, even at its worst run's estimate
    window: tuple | None = SCORING_WINDOW  # score only a (height, width) window around the footprint (None: whole image)
    target_ess: float = 0.5        # of the incremental weights, as a share of the particles
    max_temperatures: int = 100    # a run that needs more jumps to lambda = 1 (statistics: 'forced')
    draws: int = 400               # posterior draws returned (resampled from the mixture)
    # NP3 only: start from P3's final particles and temper the neural term in (:func:`bridge`),
    # rather than temper all of NP3's likelihood in from the prior
    bridge: bool = True
    seed: int = 0

    def __post_init__(self):
        from ..errors import ConfigError, check_counts

        check_counts(self, {"particles": 4, "oversample": 1, "mcmc_steps": 1, "material_every": 1, "final_steps": 0,
                            "islands": 1, "rounds": 1, "max_temperatures": 1, "draws": 4, "seed": 0, "ridge": 0}, "smc ")
        if not 0.0 < self.target_ess < 1.0:
            raise ConfigError(f"smc target-ess must lie in (0, 1); got {self.target_ess}")
        if not 0.0 < self.decided <= 1.0:
            raise ConfigError(f"smc decided must lie in (0, 1]; got {self.decided}")
        if self.window is not None:
            window = tuple(self.window)
            if len(window) != 2 or not all(isinstance(v, (int, np.integer)) and v >= 8 for v in window):
                raise ConfigError(f"smc window must be (height, width) in pixels, each at least 8; got {self.window}")
            object.__setattr__(self, "window", tuple(int(v) for v in window))


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


class Kernels(NamedTuple):
    """The jitted functions of one core's SMC (see :func:`_kernels`)."""
    score: Callable
    walk: Callable
    material: Callable
    parts: Callable


@functools.lru_cache(maxsize=4)
def _kernels(core, walk_mask: tuple, kinds: bool, ridge: int = 0) -> Kernels:
    """Jitted kernels for one :class:`PosteriorCore`: scores of all particles, the two moves of all
    particles at per-row temperatures, and (for the bridge) the colour and whole log likelihood of
    all particles from one render each. Every row is one run of one hypothesis; ``index`` (R,) names
    each row's hypothesis (a row of :func:`hypotheses_of` without islands)."""
    import jax
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import RWState

    log_prior = hypothesis_log_prior(core.prior, hypotheses_of(core.prior, kinds))
    mask = jnp.asarray(walk_mask, jnp.float32)

    def loglik_all(z, observation):                               # (R, N, d) -> (R, N)
        flat = z.reshape(-1, z.shape[-1])
        return jax.vmap(lambda p: core.log_likelihood(p, observation))(flat).reshape(z.shape[:2])

    def logprior_all(z, index):
        h = jnp.broadcast_to(index[:, None], z.shape[:2])
        return jax.vmap(jax.vmap(log_prior))(z, h)

    @jax.jit
    def score(z, index, observation):
        return loglik_all(z, observation), logprior_all(z, index)

    @jax.jit
    def parts(z, index, observation):
        colour, whole = jax.vmap(lambda p: core.log_likelihood_parts(p, observation))(z.reshape(-1, z.shape[-1]))
        return colour.reshape(z.shape[:2]), whole.reshape(z.shape[:2]), logprior_all(z, index)

    @jax.jit
    def walk(key, state, index, tempering, tril, observation):
        """The random walk, then the symmetry move; returns (state, walk acceptance (R,))."""
        k_walk, k_accept, k_symmetry = jax.random.split(key, 3)
        z, loglik, logprior = state
        noise = jax.random.normal(k_walk, z.shape) * mask
        proposed = z + jnp.einsum("hij,hnj->hni", tril, noise)
        new_loglik, new_logprior = loglik_all(proposed, observation), logprior_all(proposed, index)
        log_ratio = new_logprior + tempering[:, None] * new_loglik - logprior - tempering[:, None] * loglik
        accept = jnp.log(jax.random.uniform(k_accept, loglik.shape)) < log_ratio
        z = jnp.where(accept[..., None], proposed, z)
        loglik, logprior = jnp.where(accept, new_loglik, loglik), jnp.where(accept, new_logprior, logprior)
        # symmetry: no render; the tempered density changes only through the yaw prior
        flat = RWState(z.reshape(-1, z.shape[-1]), logprior.reshape(-1))
        turned = jax.vmap(core.symmetry_move)(jax.random.split(k_symmetry, flat.position.shape[0]), flat)
        if ridge:
            # along the colour/weight ridge: no render; the density changes by the hypothesis prior's difference
            h = jnp.repeat(index, z.shape[1])
            for k_ridge in jax.random.split(jax.random.fold_in(k_symmetry, 1), ridge):
                turned = jax.vmap(lambda key, state, row: core.ridge_move(key, state, lambda p: log_prior(p, row)))(
                    jax.random.split(k_ridge, flat.position.shape[0]), turned, h)
        return SMCState(turned.position.reshape(z.shape), loglik, turned.logdensity.reshape(logprior.shape)), \
            accept.mean(axis=1)

    @jax.jit
    def material(key, state, index, tempering, observation):
        """The material Metropolis-within-Gibbs update at each row's temperature (one render of
        the material bases per particle; the result is scored from them)."""
        z, loglik, logprior = state
        h = jnp.repeat(index, z.shape[1])
        lam = jnp.repeat(tempering, z.shape[1])

        def one(key, position, logprior_value, loglik_value, row_hypothesis, lam_value):
            state = RWState(position, logprior_value + lam_value * loglik_value)
            new, _, new_loglik = core.scored_material_move(key, state, observation, lam_value,
                                                           lambda p: log_prior(p, row_hypothesis))
            return new.position, new_loglik

        keys = jax.random.split(key, h.shape[0])
        moved, new_loglik = jax.vmap(one)(keys, z.reshape(-1, z.shape[-1]), logprior.reshape(-1),
                                          loglik.reshape(-1), h, lam)
        moved = moved.reshape(z.shape)
        return SMCState(moved, new_loglik.reshape(loglik.shape), logprior_all(moved, index))

    return Kernels(score, walk, material, parts)


def _move(kernels, state: SMCState, index, tempering: np.ndarray, scale: np.ndarray, sweeps: int,
          material_every: int, key, observation) -> tuple[SMCState, np.ndarray, object]:
    """``sweeps`` walk sweeps of every row at its temperature, each ``material_every``-th and the
    last followed by the material update; each row's walk covariance is 2.38^2 / d times its own
    particles' (moved dimensions only) times its ``scale``. Returns the moved particles (numpy),
    each row's walk acceptance and the key, split once per sweep."""
    import jax
    import jax.numpy as jnp

    walk, material = kernels.walk, kernels.material
    moved = WALK_MASK > 0
    z = np.asarray(state.position)
    tril = np.zeros((len(z), DIMENSION, DIMENSION), np.float32)
    for h in range(len(z)):
        cov = np.cov(z[h][:, moved], rowvar=False) + 1e-6 * np.eye(moved.sum())
        tril[h][np.ix_(moved, moved)] = np.linalg.cholesky(cov) * 2.38 / np.sqrt(moved.sum()) * scale[h]
    state = SMCState(*(jnp.asarray(a) for a in state))
    lam, tril = jnp.asarray(tempering, jnp.float32), jnp.asarray(tril)
    rates = []
    for i in range(sweeps):
        key, k_walk, k_material = jax.random.split(key, 3)
        state, accepted = walk(k_walk, state, index, lam, tril, observation)
        rates.append(np.asarray(accepted))
        if (i + 1) % material_every == 0 or i == sweeps - 1:
            state = material(k_material, state, index, lam, observation)
    return SMCState(*(np.array(a) for a in state)), np.mean(rates, axis=0), key


class Rows(NamedTuple):
    """The outcome of tempering some rows (independent runs) to lambda = 1: each row's hypothesis,
    particles, log evidence estimate and temperature count."""
    index: np.ndarray
    state: SMCState
    log_evidence: np.ndarray
    temperatures: int
    acceptance: list


def temper(core, observation, index: np.ndarray, config: SMCConfig, rng: np.random.Generator, key,
           progress: Callable[[str, int, int], None] | None = None, image: np.ndarray | None = None) -> Rows:
    """One tempered SMC per row, all rows in the same batched renders; row r runs hypothesis
    ``index[r]`` (see the module docstring for the steps). ``image``: the whole image, whose
    footprint places the first draws (default: the observation's, when it is not a window)."""
    import jax.numpy as jnp

    kernels = _kernels(core, tuple(WALK_MASK.tolist()), config.kinds, config.ridge)
    score = kernels.score
    space = hypotheses_of(core.prior, config.kinds)
    rows = Hypotheses(tuple(space.names[i] for i in index), *(a[index] for a in space[1:]))
    count, n = len(index), config.particles
    index_j = jnp.asarray(index, jnp.int32)
    # the first reweighting starts from oversample x N prior draws and keeps N: a valid SMC step
    # (its evidence increment averages over all draws) that finds the object with few particles
    draws = initial_particles(core.prior, rng, n * config.oversample, rows)
    image = observation["image"] if image is None else image
    offset = footprint_start(core, image, draws, rng) if config.footprint else np.zeros(draws.shape[:2])
    all_loglik, all_logprior = (np.asarray(a) for a in score(jnp.asarray(draws), index_j, observation))
    z = np.empty((count, n) + draws.shape[2:], np.float32)
    loglik, logprior = np.empty((count, n), np.float32), np.empty((count, n), np.float32)
    tempering, log_evidence = np.zeros(count), np.zeros(count)
    for h in range(count):
        ll = np.where(np.isfinite(all_loglik[h]), all_loglik[h], -1e30)
        step = next_increment(ll, 1.0, config.target_ess / config.oversample, offset[h])
        log_evidence[h] = np.logaddexp.reduce(step * ll + offset[h]) - np.log(len(ll))
        tempering[h] = step
        chosen = systematic_resample(rng, step * ll + offset[h], n)
        z[h], loglik[h], logprior[h] = draws[h][chosen], all_loglik[h][chosen], all_logprior[h][chosen]
    scale = np.full(count, 1.0)
    acceptance_history, steps = [], 0
    while steps < config.max_temperatures:
        steps += 1
        for h in range(count):
            if tempering[h] >= 1.0 or steps == 1:   # the first step's reweighting is done above
                continue
            ll = np.where(np.isfinite(loglik[h]), loglik[h], -1e30)
            step = next_increment(ll, 1.0 - tempering[h], config.target_ess)
            if steps == config.max_temperatures:
                step = 1.0 - tempering[h]
            log_w = step * ll
            log_evidence[h] += np.logaddexp.reduce(log_w) - np.log(len(log_w))
            tempering[h] = min(1.0, tempering[h] + step)
            chosen = systematic_resample(rng, log_w)
            z[h], loglik[h], logprior[h] = z[h][chosen], loglik[h][chosen], logprior[h][chosen]
        sweeps = config.mcmc_steps + (config.final_steps if np.all(tempering >= 1.0) else 0)
        (z, loglik, logprior), rate, key = _move(kernels, SMCState(z, loglik, logprior), index_j, tempering, scale,
                                                 sweeps, config.material_every, key, observation)
        scale *= np.clip(np.exp(2.0 * (rate - 0.25)), 0.5, 2.0)   # towards 25% walk acceptance
        acceptance_history.append(rate.tolist())
        if progress:
            progress("smc", int(100 * tempering.min()), 100)
        if np.all(tempering >= 1.0):
            break
    return Rows(np.asarray(index), SMCState(z, loglik, logprior), log_evidence, steps, acceptance_history)


def _per_hypothesis(rows: Rows, hypotheses: int, reduce: Callable[[np.ndarray], float]) -> np.ndarray:
    """``reduce`` of each hypothesis's rows' log evidence estimates (-inf: no row)."""
    return np.array([reduce(mine) if len(mine := rows.log_evidence[rows.index == h]) else -np.inf
                     for h in range(hypotheses)])


def pooled_evidence(rows: Rows, hypotheses: int) -> np.ndarray:
    """log Z_h per hypothesis: the log of the mean of its rows' unbiased estimates (-inf: no row)."""
    return _per_hypothesis(rows, hypotheses, lambda mine: np.logaddexp.reduce(mine) - np.log(len(mine)))


def island_range(rows: Rows, hypotheses: int) -> tuple[np.ndarray, np.ndarray]:
    """Per hypothesis the lowest and the highest log evidence any of its runs estimated (-inf: no run)."""
    return _per_hypothesis(rows, hypotheses, np.min), _per_hypothesis(rows, hypotheses, np.max)


def decision(log_prior: np.ndarray, pooled: np.ndarray, low: np.ndarray, high: np.ndarray,
             threshold: float) -> tuple[bool, np.ndarray]:
    """Is the answer decided, and which hypotheses are still in contention?

    The runs of one hypothesis disagree by their Monte Carlo error (a run that missed the pose
    estimates far too low), so the decision is checked against it: the leader (highest pooled
    posterior weight) is decided only if it keeps weight ``threshold`` when it takes its *lowest*
    run's estimate and every other hypothesis its *highest*. A hypothesis stays in contention if,
    at its highest run's estimate against the others' lowest, its weight reaches (1 - threshold) / H.
    With one run per hypothesis this is the plain rule on the pooled weights."""
    count = len(pooled)
    leader = int(np.argmax(log_prior + pooled))
    worst = log_prior + np.where(np.arange(count) == leader, low, high)
    decided = bool(np.exp(worst[leader] - np.logaddexp.reduce(worst)) >= threshold)
    open_ = np.zeros(count, bool)
    for h in range(count):
        best = log_prior + np.where(np.arange(count) == h, high, low)
        open_[h] = np.exp(best[h] - np.logaddexp.reduce(best)) >= (1.0 - threshold) / count
    return decided, np.flatnonzero(open_)


def _joined(parts: list[Rows]) -> Rows:
    return Rows(np.concatenate([p.index for p in parts]),
                SMCState(*(np.concatenate([p.state[i] for p in parts]) for i in range(3))),
                np.concatenate([p.log_evidence for p in parts]), max(p.temperatures for p in parts),
                [a for p in parts for a in p.acceptance])


def shape_weights(statistics: dict) -> dict:
    """p(shape | I) from a run's statistics: each shape's hypotheses' weights summed (with material
    kinds as hypotheses, ``sphere/shiny`` and ``sphere/matte`` are both the sphere's)."""
    weights = {shape: 0.0 for shape in SHAPES}
    for name, hypothesis in statistics["hypotheses"].items():
        weights[name.split("/")[0]] += hypothesis["weight"]
    return weights


def bridge(core, observation, start: Rows, config: SMCConfig, rng: np.random.Generator, key,
           progress: Callable[[str, int, int], None] | None = None) -> Rows:
    """From P3's posterior to NP3's: temper the neural term in, starting from P3's final particles.

    NP3's likelihood is P3's colour likelihood times the neural term, so with ``start`` the rows
    of P3's run (every row at lambda = 1 of the colour likelihood) and ``core`` NP3's, the targets

        p(z | h) p_colour(I | z) p_neural(I | z)^lambda,   lambda from 0 to 1,

    lead from P3's posterior to NP3's, and each row's log evidence grows from P3's estimate by the
    log mean of every increment's weights, exp(dlambda log p_neural): Z_NP3 = Z_P3 E_P3[p_neural].
    The steps are :func:`temper`'s (ESS-chosen increments, one lambda for all rows since the
    observation carries the neural weight, systematic resampling, ``mcmc_steps`` sweeps and
    ``final_steps`` more at lambda = 1): with P3's run before them they make one SMC sampler from
    the prior to NP3's posterior, so the estimate is as unbiased as a run from the prior, and far
    cheaper when the neural term moves the posterior little, as on this project's data (a few nats
    beside colour terms of hundreds: one or two increments)."""
    import jax.numpy as jnp

    if core.config.kind != "np3":
        from ..errors import MitsubaP3Error

        raise MitsubaP3Error("the bridge tempers the neural term in: it needs the np3 likelihood's core")
    kernels = _kernels(core, tuple(WALK_MASK.tolist()), config.kinds, config.ridge)
    index = jnp.asarray(start.index, jnp.int32)
    weight = np.float32(core.config.neural_weight)
    weighted = lambda w: {**observation, "neural_weight": np.float32(w)}  # noqa: E731

    def colour_and_neural(z):
        colour, whole, logprior = (np.asarray(a, np.float64) for a in kernels.parts(z, index, weighted(weight)))
        return colour, whole - colour, logprior

    z = np.asarray(start.state.position, np.float32)
    log_evidence = np.array(start.log_evidence, np.float64)
    scale, lam, steps, acceptance = np.ones(len(z)), 0.0, 0, []
    while lam < 1.0 and steps < config.max_temperatures:
        steps += 1
        colour, neural, logprior = colour_and_neural(z)
        neural = np.where(np.isfinite(neural), neural, -1e30)
        step = min(next_increment(neural[h], 1.0 - lam, config.target_ess) for h in range(len(z)))
        if steps == config.max_temperatures:
            step = 1.0 - lam
        for h in range(len(z)):
            log_w = step * neural[h]
            log_evidence[h] += np.logaddexp.reduce(log_w) - np.log(len(log_w))
            chosen = systematic_resample(rng, log_w)
            z[h], colour[h], neural[h], logprior[h] = z[h][chosen], colour[h][chosen], neural[h][chosen], \
                logprior[h][chosen]
        lam = 1.0 if 1.0 - (lam + step) < 1e-9 else lam + step
        loglik = (colour + lam * neural).astype(np.float32)
        sweeps = config.mcmc_steps + (config.final_steps if lam >= 1.0 else 0)
        state, rate, key = _move(kernels, SMCState(z, loglik, logprior.astype(np.float32)), index,
                                 np.ones(len(z)), scale, sweeps, config.material_every, key, weighted(lam * weight))
        z = state.position
        scale *= np.clip(np.exp(2.0 * (rate - 0.25)), 0.5, 2.0)
        acceptance.append(rate.tolist())
        if progress:
            progress("bridge", int(100 * lam), 100)
    return Rows(np.asarray(start.index), state, log_evidence, start.temperatures + steps, start.acceptance + acceptance)


class Particles(NamedTuple):
    """An SMC run's final particles, kept so that another likelihood's run can start from them
    (:func:`bridge`): its rows and the window its likelihood scored (None: the whole image)."""
    rows: Rows
    window: tuple | None


def check_sampler_memory(config: SMCConfig, hypotheses: int, pixels: int, limit: float | None = None) -> None:
    """Refuse, before any render, settings whose widest step (the first reweighting: every hypothesis's
    ``islands`` x ``particles`` x ``oversample`` draws of ``pixels`` each, as material bases) would need
    more memory than ``limit`` bytes (default: the renderer's, :func:`~mitsuba_p3.render.contract.memory_limit`),
    with the largest particle count that fits."""
    from ..errors import InferenceError
    from ..render.contract import BYTES_PER_PIXEL, memory_limit

    limit = memory_limit() if limit is None else limit
    renders = hypotheses * config.islands * config.particles * config.oversample
    need = renders * pixels * BYTES_PER_PIXEL["bases"]
    if need > limit:
        fits = int(limit // (hypotheses * config.islands * config.oversample * pixels * BYTES_PER_PIXEL["bases"]))
        raise InferenceError(f"{config.particles:,} particles: the SMC's first step renders {renders:,} images of "
                             f"{pixels:,} pixels, about {need / 2 ** 30:,.1f} GB, over the limit of "
                             f"{limit / 2 ** 30:.1f} GB; use --particles {max(fits, 4)} or fewer (or set "
                             "MITSUBA_P3_MEMORY_GB)")


def sample_smc(core, observation, config: SMCConfig | None = None,
               progress: Callable[[str, int, int], None] | None = None,
               start: Particles | None = None) -> SamplerRun:
    """Tempered SMC of every hypothesis of one image (see the module docstring). With ``start``,
    P3's final particles of the same image and sampler settings, ``core`` being NP3's, the run
    is :func:`bridge`'s instead: from P3's posterior to NP3's, on the window P3 scored."""
    import jax

    config = config or SMCConfig()
    begin = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    key = jax.random.PRNGKey(config.seed)
    space = hypotheses_of(core.prior, config.kinds)
    count = len(space.names)
    image = np.asarray(observation["image"])
    scored = config.window or image.shape[:2]
    check_sampler_memory(config, count, int(np.prod(scored)))
    window = None
    if start is not None:
        window = start.window
        if "window" not in observation:
            observation = core.observe(image, window) if window else observation
        # streams of their own: P3's run used the seed's, and the bridge's moves must not repeat them
        rng, key = np.random.default_rng([config.seed, 1]), jax.random.fold_in(key, 1)
        rows, rounds = bridge(core, observation, start.rows, config, rng, key, progress), 1
        pooled = pooled_evidence(rows, count)
    else:
        if config.window and "window" not in observation:
            window = core.window_for(image, tuple(config.window))
            observation = core.observe(image, window) if window else observation
        rows, pooled, rounds = _rounds(core, observation, image, space, config, rng, key, progress)
    run = _sampler_run(core, rows, pooled, space, config, rng, window, rounds, time.perf_counter() - begin)
    run.statistics.update(object_evidence(core, observation, rows, space, pooled))
    return run


# a half-extent this small (metres) is far below a pixel: the render is the empty floor
EMPTY_SCALE = 1e-5


def object_evidence(core, observation, rows: Rows, space: Hypotheses, pooled: np.ndarray) -> dict:
    """Whether the image shows an object the model explains: the log evidence of "one object" (the
    hypotheses' evidence under their prior) against the empty floor, a model without parameters whose
    evidence is its likelihood, scored on the same window by the same likelihood. A negative log
    Bayes factor says the floor alone explains the image better than any object would."""
    import jax.numpy as jnp

    z = np.array(rows.state.position[0, 0], np.float32)
    z[SLICES["scale"]] = np.log(EMPTY_SCALE)
    empty = float(core.log_likelihood(jnp.asarray(z), observation))
    one_object = float(np.logaddexp.reduce(space.log_prior + pooled))
    return {"empty_log_likelihood": empty, "log_bayes_factor_object": one_object - empty}


def _rounds(core, observation, image, space: Hypotheses, config: SMCConfig, rng, key, progress):
    """Round 1: islands x every hypothesis; later rounds: islands x those still in contention."""
    import jax

    count = len(space.names)
    contenders, parts = np.arange(count), []
    for _ in range(config.rounds):
        key, k_round = jax.random.split(key)
        parts.append(temper(core, observation, np.tile(contenders, config.islands), config, rng, k_round, progress,
                            image))
        rows = _joined(parts)
        pooled = pooled_evidence(rows, count)
        low, high = island_range(rows, count)
        decided, contenders = decision(space.log_prior, pooled, low, high, config.decided)
        if decided or len(contenders) < 2:
            break
    return rows, pooled, len(parts)


def _sampler_run(core, rows: Rows, pooled: np.ndarray, space: Hypotheses, config: SMCConfig,
                 rng: np.random.Generator, window, rounds: int, seconds: float) -> SamplerRun:
    """Draws from the mixture over hypotheses, each hypothesis weighed by its pooled evidence, and the
    run's statistics; the final particles ride along (``particles``) for a bridge to start from."""
    count = len(space.names)
    log_posterior = space.log_prior + pooled
    weights = np.exp(log_posterior - np.logaddexp.reduce(log_posterior))
    # a row's share of its hypothesis is its own estimate's share of the hypothesis's sum
    row_weights = np.zeros(len(rows.index))
    for h in range(count):
        mine = rows.index == h
        if mine.any():
            row_weights[mine] = weights[h] * np.exp(rows.log_evidence[mine]
                                                    - np.logaddexp.reduce(rows.log_evidence[mine]))
    # draws: rows by their posterior weight, particles uniformly (equal weights after resampling). One
    # pool, not chains: draws cut from one pool would agree by construction, so no R-hat is made of
    # them; the runs' agreement is the island gap below (and R-hat across seeds, scripts/bench_infer.py)
    z, loglik, logprior = rows.state
    draws = max(1, config.draws)
    chosen_row = rng.choice(len(row_weights), size=draws, p=row_weights / row_weights.sum())
    chosen_n = rng.integers(config.particles, size=draws)
    positions = z[chosen_row, chosen_n].reshape(1, draws, -1)
    logdensity = (logprior + loglik)[chosen_row, chosen_n].reshape(1, draws)
    shiny_rows = (z[..., SLICES["specular"].start] > core.prior.specular_threshold()).mean(axis=1)
    statistics = {"hypotheses": {}, "rounds": rounds, "temperatures": rows.temperatures,
                  "window": list(window) if window else None,
                  "forced": bool(rows.temperatures == config.max_temperatures),
                  "walk_acceptance": float(np.mean(rows.acceptance[-1])), "seconds": seconds}
    for h, name in enumerate(space.names):
        mine = rows.index == h
        share = row_weights[mine] / max(row_weights[mine].sum(), 1e-300)
        best = loglik[mine]
        statistics["hypotheses"][name] = {"log_evidence": float(pooled[h]), "weight": float(weights[h]),
                                          "shiny": float(np.sum(shiny_rows[mine] * share)),
                                          "runs": int(mine.sum()),
                                          # the highest log likelihood any final particle reached: beside the
                                          # likelihood at the truth it tells a run that missed the peak
                                          "max_log_likelihood": float(best.max()) if best.size else None,
                                          # each run's own estimate of log Z_h: their spread is the Monte
                                          # Carlo error of the evidence that decides the hypotheses
                                          "island_log_evidence": rows.log_evidence[mine].tolist()}
    statistics["island_gap"] = island_gap(statistics)
    return SamplerRun(positions.astype(np.float32), logdensity.astype(np.float32), None, {},
                      [{"acceptance": a} for a in rows.acceptance],
                      {"sampler": "smc", **asdict(config)}, statistics, Particles(rows, window))


def island_gap(statistics: dict) -> float | None:
    """The spread (max - min, nats) of the leading hypothesis's runs' log evidence: how far two
    independent SMC runs of the answer disagree. About sqrt(T / N) nats when they explored alike; tens
    of nats when one run missed the pose the other found. None with a single run."""
    hypotheses = statistics["hypotheses"]
    leader = max(hypotheses, key=lambda name: hypotheses[name]["weight"])
    runs = hypotheses[leader].get("island_log_evidence") or []
    return float(max(runs) - min(runs)) if len(runs) > 1 else None
