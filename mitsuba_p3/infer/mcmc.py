"""Random-walk Metropolis-Hastings over many chains at once (blackjax kernels, a jitted JAX loop).

Phases, all seeded:

1. **Initialisation.** Draw ``init_candidates`` positions from the prior, score
   them in batches, and start the chains at the best distinct ones. This is a
   cheap importance search that saves most of the burn-in.
2. **Tuning.** ``tune_rounds`` rounds of ``tune_steps``. After each round the
   proposal becomes a full-covariance Gaussian: the covariance of the round's
   draws (each chain centred on its own mean, so chains sitting in different
   places do not inflate it), times 2.38^2/d (adaptive Metropolis, Haario et
   al. 2001), times a global factor moved until the acceptance rate falls in
   ``target_acceptance`` (20-50%). The paper's single scalar sigma mixes poorly:
   colour, k_a and k_d are strongly correlated, and the dimensions differ in scale.
   After each round, chains stuck in a mode whose mean log density is more than
   ``cull_margin`` nats below the best chain's are restarted from a randomly
   chosen good chain (only during tuning; modes of similar density all survive).
3. **Burn-in**, then **sampling** with the proposal fixed, so the kept draws
   come from one valid MH kernel.

The proposal is a symmetric mixture: usually a Gaussian step on every
dimension; with probability ``class_jump_probability`` a wide step on the two
class logits only, so chains can move between shape classes.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Callable, NamedTuple

import numpy as np

from ..fit.priors import SLICES


@dataclass
class SamplerConfig:
    chains: int = 20
    steps: int = 1000            # kept draws per chain
    burn_in: int = 200
    tune_rounds: int = 5
    tune_steps: int = 200
    initial_scale: float = 0.05
    target_acceptance: tuple = (0.2, 0.5)
    class_jump_probability: float = 0.1
    class_jump_scale: float = 3.0
    init_candidates: int = 400
    cull_margin: float = 20.0    # nats
    block: int = 50              # steps per compiled call (progress granularity)
    seed: int = 0


class SamplerRun(NamedTuple):
    positions: np.ndarray         # (chains, draws, 15) unconstrained
    logdensity: np.ndarray        # (chains, draws)
    accepted: np.ndarray          # (chains, draws) bool
    scales: np.ndarray            # (15, 15) final proposal: lower-triangular factor of its covariance
    tuning: list                  # per round: acceptance, factor
    config: dict


def _random_step(scale_tril, jump_probability: float, jump_scale: float):
    """Symmetric proposal: N(0, L L^T), or, with ``jump_probability``, a wide step on the class logits."""
    import jax
    import jax.numpy as jnp

    kappa = np.zeros(scale_tril.shape[0], np.float32)
    kappa[SLICES["kappa"]] = 1.0

    def step(key, position):
        k_choice, k_noise = jax.random.split(key)
        noise = jax.random.normal(k_noise, position.shape)
        jump = jax.random.uniform(k_choice) < jump_probability
        return jnp.where(jump, noise * jump_scale * kappa, scale_tril @ noise)

    return step


def _block_runner(logdensity_fn: Callable, config: SamplerConfig):
    """A jitted function running ``config.block`` MH steps of every chain."""
    import jax
    from blackjax.mcmc.random_walk import build_additive_step

    kernel = build_additive_step()

    @jax.jit
    def run(key, states, scales):
        step_fn = _random_step(scales, config.class_jump_probability, config.class_jump_scale)

        def one_step(states, key):
            keys = jax.random.split(key, config.chains)
            states, info = jax.vmap(lambda k, s: kernel(k, s, logdensity_fn, step_fn))(keys, states)
            return states, (states.position, states.logdensity, info.is_accepted)

        return jax.lax.scan(one_step, states, jax.random.split(key, config.block))

    return run


def _cull(states, logdensity: np.ndarray, margin: float, rng: np.random.Generator):
    """Restart chains whose mean log density (last half of a round) trails the best by > margin."""
    import jax.numpy as jnp

    recent = logdensity[len(logdensity) // 2:].mean(axis=0)
    good = np.flatnonzero(recent >= recent.max() - margin)
    bad = np.flatnonzero(recent < recent.max() - margin)
    if len(bad) == 0:
        return states, 0
    source = np.arange(len(recent))
    source[bad] = rng.choice(good, size=len(bad))
    index = jnp.asarray(source)
    return type(states)(states.position[index], states.logdensity[index]), int(len(bad))


def initial_positions(logdensity_fn: Callable, prior, config: SamplerConfig, rng: np.random.Generator):
    """The best ``chains`` of ``init_candidates`` prior draws (batched evaluation)."""
    import jax

    candidates = prior.sample(rng, max(config.init_candidates, config.chains)).astype(np.float32)
    scores = np.asarray(jax.jit(jax.vmap(logdensity_fn))(candidates))
    scores = np.where(np.isfinite(scores), scores, -np.inf)
    return candidates[np.argsort(-scores)[:config.chains]]


def sample(logdensity_fn: Callable, prior, config: SamplerConfig | None = None,
           progress: Callable[[str, int, int], None] | None = None) -> SamplerRun:
    """Run initialisation, tuning, burn-in and sampling; returns the kept draws."""
    import jax
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import init

    config = config or SamplerConfig()
    rng = np.random.default_rng(config.seed)
    key = jax.random.PRNGKey(config.seed)
    start = initial_positions(logdensity_fn, prior, config, rng)
    states = jax.vmap(lambda z: init(z, logdensity_fn))(jnp.asarray(start))
    run = _block_runner(logdensity_fn, config)
    dimension = start.shape[1]
    scales = np.eye(dimension, dtype=np.float32) * config.initial_scale
    factor = 1.0
    tuning = []
    blocks_per_round = max(1, -(-config.tune_steps // config.block))
    total = (config.tune_rounds * blocks_per_round + -(-config.burn_in // config.block)
             + -(-config.steps // config.block)) * config.block
    done = 0

    def advance(states, phase):
        nonlocal key, done
        key, sub = jax.random.split(key)
        states, (positions, logdensity, accepted) = run(sub, states, jnp.asarray(scales))
        done += config.block
        if progress:
            progress(phase, done, total)
        return states, np.asarray(positions), np.asarray(logdensity), np.asarray(accepted)

    low, high = config.target_acceptance
    for round_index in range(config.tune_rounds):
        positions, logdensities, accepted = [], [], []
        for _ in range(blocks_per_round):
            states, p, l, a = advance(states, "tuning")
            positions.append(p)
            logdensities.append(l)
            accepted.append(a)
        positions, acceptance = np.concatenate(positions), float(np.mean(np.concatenate(accepted)))
        states, culled = _cull(states, np.concatenate(logdensities), config.cull_margin, rng)
        if acceptance < low:
            factor *= 0.5 if acceptance < low / 2 else 0.75
        elif acceptance > high:
            factor *= 2.0 if acceptance > (1 + high) / 2 else 1.4
        centred = (positions - positions.mean(axis=0, keepdims=True)).reshape(-1, dimension)
        covariance = np.cov(centred, rowvar=False) + 1e-8 * np.eye(dimension)
        base = np.linalg.cholesky(covariance) * 2.38 / np.sqrt(dimension)
        scales = (base * factor).astype(np.float32)
        tuning.append({"round": round_index, "acceptance": acceptance, "factor": factor, "restarted": culled})

    for _ in range(-(-config.burn_in // config.block)):
        states, *_ = advance(states, "burn-in")
    positions, logdensity, accepted = [], [], []
    for _ in range(-(-config.steps // config.block)):
        states, p, l, a = advance(states, "sampling")
        positions.append(p)
        logdensity.append(l)
        accepted.append(a)
    # scan stacks (steps, chains, ...): move chains first and trim to the requested count
    positions = np.concatenate(positions).swapaxes(0, 1)[:, :config.steps]
    logdensity = np.concatenate(logdensity).swapaxes(0, 1)[:, :config.steps]
    accepted = np.concatenate(accepted).swapaxes(0, 1)[:, :config.steps]
    return SamplerRun(positions, logdensity, accepted, scales, tuning, asdict(config))
