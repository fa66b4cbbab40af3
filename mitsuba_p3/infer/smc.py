"""Tempered sequential Monte Carlo over the discrete hypotheses: the shape classes.

A random walk over a relaxed one-hot class cannot cross between shape modes once the
likelihood is sharp. Here each hypothesis h (sphere, cube or cylinder;
:mod:`mitsuba_p3.infer.hypotheses`) is a posterior of its own over the continuous
parameters, and its *evidence* Z_h = p(I | h) decides between them:

    p(h | I) = p(h) Z_h / sum_h' p(h') Z_h',    p(h) the prior's class probability.

Each hypothesis runs a tempered SMC (:mod:`mitsuba_p3.infer.tempering`: N particles move
through p(z | h) p(I | z)^lambda as lambda rises from 0 to 1, and the run estimates log Z_h)
with the moves of :mod:`mitsuba_p3.infer.smc_moves` (where JAX runs on a GPU, a plain step is one
compiled call on the device: :mod:`mitsuba_p3.infer.device_step`). All runs of all hypotheses are rows
of one state, scored in one batched render per move. This module is the layer that makes
scenes of it:

**The first step starts from the image.** It draws ``oversample`` x N scenes per
hypothesis, half from the prior and half with their position taken from the image's
footprint, weighs each by prior / (the mixture of both) times its likelihood^lambda_1, and
keeps N: an importance-sampling step whose evidence estimate is unbiased, so the footprint
makes the search cheaper without changing what is estimated.

**A window around the object.** With ``window=(h, w)`` the likelihood scores only an h x w
window centred on the largest connected part of the image's footprint
(:meth:`~mitsuba_p3.infer.model.PosteriorCore.window_for`), and every render of the run traces
only those pixels. Every hypothesis is scored on the same pixels, so their evidences stay
comparable; an image whose footprint does not fit the window is scored whole. The window's
pixels stand for the whole image only while the object is in it, so a scene whose object's
centre lies outside it has likelihood zero (``inside_window``,
:mod:`mitsuba_p3.infer.window`).

**A coarse wide start.** The first ``wide_steps`` temperatures, where the pose is chosen, move
``wide`` x N particles scored at 1 / ``coarse`` of the resolution (:mod:`mitsuba_p3.infer.coarse`:
four times the particles for the pixels' cost at the default 2); the step after them weighs each
particle by the ratio of the full and the coarse tempered likelihoods and resamples to N, so the
evidence stays the full likelihood's.

**Islands and rounds.** ``islands=k`` runs k independent SMCs per hypothesis; their unbiased
estimates of Z_h pool as their mean (:mod:`mitsuba_p3.infer.evidence`), and their spread is the
run's convergence diagnostic (the island gap). ``rounds=r`` spends more runs only where the
answer is still open: after each round, unless the leader is decided against the runs' own
disagreement (:func:`~mitsuba_p3.infer.evidence.decision`), another round runs ``islands`` more
SMCs of the hypotheses still in contention. The default is up to two rounds (chosen on the train
images of five worlds); a decided image runs one round only, so the cost is paid where the islands
disagree.
The draws come from each run in proportion to its share of its hypothesis's pooled estimate.

**Each run's evidence, twice.** A run's tempered estimate of log Z_h carries its path's error: two runs that
end at one optimum can disagree by several nats. With ``importance`` draws (the default 256) each run
also estimates its evidence by importance sampling from a Student-t fitted to its own final particles
(:mod:`mitsuba_p3.infer.importance`) and keeps the mean of the two unbiased estimates, which two
runs agree on better than on either alone.

**Material kind.** By default the matte/shiny decision is left inside each shape's run (the
specular weight keeps the prior's two-component mixture; p(shiny | h, I) is the particles'
share above the prior's threshold). ``kinds=True`` makes shape x material kind six hypotheses
of their own instead (twice the cost).

**An image's own noise scale** (``--noise scaled``): each run searches under the fixed scale, then bridges
the scale in (:mod:`mitsuba_p3.infer.bridge`, which says why); the rounds' decision reads the bridged evidence.

**NP3 from P3's posterior.** NP3's run starts from P3's final particles of the same image and
tempers only the neural term in (:mod:`mitsuba_p3.infer.bridge`); ``bridge=False`` runs NP3 from
the prior like P3.

**One object, or nothing?** The hypotheses' evidence, weighed by their prior, is the evidence of
"one object"; the empty floor is a model without parameters, whose evidence is its likelihood on
the same window (:func:`~mitsuba_p3.infer.evidence.object_evidence`). Their log ratio, ``log_bayes_factor_object``, is
negative when the floor alone explains the image better: ``infer`` then warns.

The result is an :class:`SMCRun`: draws from the mixture over hypotheses (one pool: no chains,
so no R-hat of them), each hypothesis's pooled and per-run log evidence, and every step's
lambda, ESS, evidence increment and acceptance per move, per run.
"""
from __future__ import annotations

import time
from dataclasses import asdict
from typing import Callable, NamedTuple

import numpy as np

from ..space import SLICES
from . import device_step, tempering
from .evidence import decision, island_gap, island_range, mark_lost_runs, object_evidence, pooled_evidence
from .budget import GPU_PARTICLES, check_sampler_memory, default_particles  # noqa: F401 (re-exported)
from .coarse import coarse_view, to_full
from .hypotheses import Hypotheses, footprint_start, hypotheses_of, initial_particles
from .importance import importance_evidence
from .smc_config import DEFAULTS_BEFORE, SMCConfig  # noqa: F401 (re-exported)
from .smc_moves import mover
from .smc_moves import kernels_for
from .window import OUTSIDE_WINDOW


class SMCState(NamedTuple):
    """The final particles of some rows: positions (R, N, d), log likelihoods and log priors (R, N)."""
    position: np.ndarray
    loglikelihood: np.ndarray
    logprior: np.ndarray


class Rows(NamedTuple):
    """The outcome of tempering some rows (independent runs) to lambda = 1: each row's hypothesis,
    final particles, log evidence estimate, the number of temperatures, and every step's record
    (:func:`mitsuba_p3.infer.tempering.record`)."""
    index: np.ndarray
    state: SMCState
    log_evidence: np.ndarray
    temperatures: int
    steps: list
    # with the importance-sampling evidence (:mod:`mitsuba_p3.infer.importance`): each row's tempered
    # estimate, its importance estimate and that one's effective sample size (R,); None without it
    tempered: np.ndarray | None = None
    importance: np.ndarray | None = None
    importance_ess: np.ndarray | None = None


class Particles(NamedTuple):
    """An SMC run's final particles, kept so that another likelihood's run can start from them
    (:mod:`mitsuba_p3.infer.bridge`): its rows and the window its likelihood scored (None: whole)."""
    rows: Rows
    window: tuple | None


class SMCRun(NamedTuple):
    """An SMC posterior: ``draws`` positions (1, draws, 15) unconstrained, resampled from the mixture
    over hypotheses (one pool, no chains), their log densities, the settings, the statistics (per
    hypothesis: pooled and per-run log evidence, weight, shiny share, best log likelihood; the
    island gap; ``steps``: per step and run lambda, ESS, evidence increment and acceptance per
    move), and the final particles for a bridge to start from."""
    positions: np.ndarray
    logdensity: np.ndarray
    config: dict
    statistics: dict
    particles: Particles


def temper(core, observation, index: np.ndarray, config: SMCConfig, rng: np.random.Generator, key,
           progress: Callable[[str, int, int], None] | None = None, image: np.ndarray | None = None) -> Rows:
    """One tempered SMC per row, all rows in the same batched renders; row r runs hypothesis
    ``index[r]``. ``image``: the whole image, whose footprint places the first draws (default: the
    observation's, when it is not a window)."""
    import jax
    import jax.numpy as jnp

    kernels = kernels_for(core, config)
    space = hypotheses_of(core.prior, config.kinds)
    rows = Hypotheses(tuple(space.names[i] for i in index), *(a[index] for a in space[1:]))
    index_j = jnp.asarray(index, jnp.int32)
    # the first step starts from oversample x N draws and keeps N: a valid SMC step (its evidence
    # increment averages over all draws) that finds the object with few particles
    draws = initial_particles(core.prior, rng, config.particles * config.oversample, rows)
    image = observation["image"] if image is None else image
    offset = footprint_start(core, image, draws, rng) if config.footprint else None
    # waste-free: resample N / P and keep every state of the P - 1 sweeps that follow
    free = config.waste_free > 1

    def moves(kernels, observation):
        return mover(kernels, index_j, observation, config.waste_free - 1 if free else config.mcmc_steps,
                     config.material_every, final_sweeps=0 if free else config.final_steps, path=free,
                     gradient_sweeps=config.gradient_steps, final_gradient_sweeps=config.final_gradient_steps)

    move = moves(kernels, observation)
    kept = config.particles // config.waste_free if free else None
    # a wide start's particles per particle, at most the oversampled draws it is resampled from; it ends a
    # step before the last temperature a run may take, so a coarse one always changes to the full likelihood
    wide_steps = min(config.wide_steps, config.max_temperatures - 1)
    width = min(config.wide, config.oversample) if wide_steps else 1
    # a coarse wide start (:mod:`mitsuba_p3.infer.coarse`): its steps score and move at 1 / coarse of the resolution
    coarse = coarse_view(core, observation, image, config.coarse) if width > 1 and config.coarse > 1 else None
    if coarse:
        start_kernels = kernels_for(coarse[0], config)
        start_observation = coarse[1]
        start_move = moves(start_kernels, start_observation)
    else:
        start_kernels, start_observation, start_move = kernels, observation, move
    state = tempering.init(draws, *start_kernels.score(jnp.asarray(draws), index_j, start_observation))
    steps, pool = [], None
    # a plain step (reweight, resample, the walks and material updates) as one compiled call where JAX runs
    # on a GPU (device_step.py); the first step, a coarse start's change, persistent sampling, waste-free SMC
    # and MALA run on the host
    on_device = (device_step.step_for() == "device" and not free and not config.persistent
                 and not (config.gradient_steps or config.final_gradient_steps))
    if on_device:       # the observed images copied to the device once, not at every step's call
        on_start, on_full = jax.device_put(start_observation), jax.device_put(observation)
    # (a coarse start that reached lambda = 1 still changes to the full likelihood before the run ends)
    while len(steps) < config.max_temperatures and (not np.all(state.tempering >= 1.0)
                                                    or coarse and len(steps) <= wide_steps):
        key, k_step = jax.random.split(key)
        first, force = not steps, len(steps) + 1 == config.max_temperatures
        if pool is not None:        # persistent sampling: reweight and resample the pool of every step so far
            state, pool, info = tempering.persistent_step(k_step, state, pool, move, config.persistent_ess, force)
        else:
            # the first step keeps N (wide x N during a wide start) of the oversampled draws; the step after
            # the wide start resamples down to N
            last_wide = width > 1 and len(steps) == wide_steps
            count = kept or (width * config.particles if first else config.particles if last_wide else None)
            wide = len(steps) < wide_steps
            if on_device and not first and not last_wide:
                state, info = device_step.step(k_step, state, start_kernels if wide else kernels, index_j,
                                               on_start if wide else on_full, config.mcmc_steps,
                                               config.material_every, config.final_steps, config.target_ess, force)
            else:
                state, change = device_step.on_host(state), None
                if coarse and last_wide:    # from the coarse target to the full one, weighed by their ratio
                    state, change = to_full(kernels, state, index_j, observation)
                state, info = tempering.step(k_step, state, start_move if wide else move,
                                             config.target_ess / (config.oversample / width if first else 1),
                                             count=count, offset=offset if first else change, force=force)
                if config.persistent:
                    pool = tempering.pool_add(None, state, config.max_temperatures)
        steps.append(tempering.record(info, index))
        if progress:
            progress("smc", int(100 * state.tempering.min()), 100)
    return Rows(np.asarray(index), SMCState(*device_step.on_host(state)[:3]), state.log_evidence, len(steps), steps)


def _joined(parts: list[Rows]) -> Rows:
    optional = lambda name: (np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
                             if all(getattr(p, name) is not None for p in parts) else None)
    return Rows(np.concatenate([p.index for p in parts]),
                SMCState(*(np.concatenate([p.state[i] for p in parts]) for i in range(3))),
                np.concatenate([p.log_evidence for p in parts]), max(p.temperatures for p in parts),
                [s for p in parts for s in p.steps], optional("tempered"), optional("importance"),
                optional("importance_ess"))


def with_importance(core, observation, rows: Rows, config: SMCConfig, rng: np.random.Generator) -> Rows:
    """``rows`` whose log evidence is the mean of each run's tempered and importance-sampling estimates
    (:mod:`mitsuba_p3.infer.importance`; ``config.importance`` draws per run; 0 leaves them as they are)."""
    if not config.importance:
        return rows
    kernels = kernels_for(core, config)
    estimate = importance_evidence(kernels.score, rows.index, rows.state.position, rows.log_evidence, observation,
                                   rng, config.importance)
    return rows._replace(log_evidence=estimate.log_evidence, tempered=rows.log_evidence,
                         importance=estimate.importance, importance_ess=estimate.ess)


def _rounds(core, observation, image, space: Hypotheses, config: SMCConfig, rng, key, progress):
    """Round 1: islands x every hypothesis; later rounds: islands x those still in contention."""
    import jax

    from .bridge import bridge

    scaled = core.config.scale is not None and "scale_weight" not in observation
    count = len(space.names)
    contenders, parts = np.arange(count), []
    for round_ in range(config.rounds):
        key, k_round = jax.random.split(key)
        # with the image's own noise scale, the search runs under the fixed scale and the scale is bridged in
        searched = {**observation, "scale_weight": np.float32(0.0)} if scaled else observation
        part = temper(core, searched, np.tile(contenders, config.islands), config, rng, k_round, progress, image)
        # a stream of its own, so that the runs themselves are what they are without the importance estimate
        part = with_importance(core, searched, part, config, np.random.default_rng([config.seed, 2, round_]))
        if scaled:
            key, k_bridge = jax.random.split(key)
            part = bridge(core, observation, part, config, k_bridge, progress, term="scale_weight")
        parts.append(part)
        rows = _joined(parts)
        pooled = pooled_evidence(rows, count)
        low, high = island_range(rows, count)
        decided, contenders = decision(space.log_prior, pooled, low, high, config.decided)
        if decided or len(contenders) < 2:
            break
    return rows, pooled, len(parts)


def outside_window(config: SMCConfig) -> float:
    """The log likelihood of a scene whose object lies outside the scoring window, under ``config``."""
    return OUTSIDE_WINDOW if config.inside_window else 0.0


def sample_smc(core, observation, config: SMCConfig | None = None,
               progress: Callable[[str, int, int], None] | None = None,
               start: Particles | None = None, window: tuple | None = None) -> SMCRun:
    """Tempered SMC of every hypothesis of one image (see the module docstring). With ``start``,
    P3's final particles of the same image and sampler settings, ``core`` being NP3's, the run
    is the bridge's instead: from P3's posterior to NP3's, on the window P3 scored. ``window``
    (top, left, height, width): score that window of the image rather than the one its footprint
    picks (SBC of the shading fields' form, whose simulated fields live on a chosen window)."""
    import jax

    from .bridge import bridge

    config = config or SMCConfig()
    begin = time.perf_counter()
    rng = np.random.default_rng(config.seed)
    key = jax.random.PRNGKey(config.seed)
    space = hypotheses_of(core.prior, config.kinds)
    count = len(space.names)
    image = np.asarray(observation["image"])
    check_sampler_memory(config, count, int(np.prod(config.window or image.shape[:2])))
    if start is not None:
        window = start.window
        if "window" not in observation:
            observation = core.observe(image, window, outside_window(config)) if window else observation
        # streams of their own: P3's run used the seed's, and the bridge's moves must not repeat them
        rng, key = np.random.default_rng([config.seed, 1]), jax.random.fold_in(key, 1)
        rows, rounds = bridge(core, observation, start.rows, config, key, progress), 1
        pooled = pooled_evidence(rows, count)
    else:
        # the window handed in (SBC's, on which its fields were drawn), else the one the footprint picks
        if window is None and config.window and "window" not in observation:
            window = core.window_for(image, tuple(config.window))
        if window is not None and "window" not in observation:
            observation = core.observe(image, tuple(window), outside_window(config))
        rows, pooled, rounds = _rounds(core, observation, image, space, config, rng, key, progress)
    run = _run(core, rows, pooled, space, config, rng, window, rounds, time.perf_counter() - begin)
    run.statistics.update(object_evidence(core, observation, rows, space, pooled))
    mark_lost_runs(run.statistics, rows, space)
    return run


def _run(core, rows: Rows, pooled: np.ndarray, space: Hypotheses, config: SMCConfig,
         rng: np.random.Generator, window, rounds: int, seconds: float) -> SMCRun:
    """Draws from the mixture over hypotheses, each weighed by its pooled evidence, and the run's
    statistics; the final particles ride along for a bridge to start from."""
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
    # them; the runs' agreement is the island gap (and R-hat across seeds, scripts/bench_infer.py)
    if not (np.all(np.isfinite(row_weights)) and row_weights.sum() > 0):
        from ..errors import InferenceError

        evidence = dict(zip(space.names, np.round(pooled, 2).tolist()))
        raise InferenceError(f"the runs' evidence is not finite (log evidence per hypothesis {evidence}); "
                             "no draws can be made")
    z, loglik, logprior = rows.state
    draws = max(1, config.draws)
    chosen_row = rng.choice(len(row_weights), size=draws, p=row_weights / row_weights.sum())
    chosen_n = rng.integers(config.particles, size=draws)
    positions = z[chosen_row, chosen_n].reshape(1, draws, -1)
    logdensity = (logprior + loglik)[chosen_row, chosen_n].reshape(1, draws)
    shiny_rows = (z[..., SLICES["specular"].start] > core.prior.specular_threshold()).mean(axis=1)
    last = rows.steps[-1] if rows.steps else {}
    statistics = {"hypotheses": {}, "rounds": rounds, "temperatures": rows.temperatures,
                  "window": list(window) if window else None,
                  "forced": bool(rows.temperatures == config.max_temperatures),
                  "walk_acceptance": float(np.mean(last.get("walk_acceptance", np.nan))),
                  "material_acceptance": float(np.mean(last.get("material_acceptance", np.nan))),
                  "seconds": seconds, "steps": rows.steps}
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
        if rows.tempered is not None:       # the two estimates the kept one is the mean of, and the weights' ESS
            statistics["hypotheses"][name].update(
                island_log_evidence_tempered=rows.tempered[mine].tolist(),
                island_log_evidence_importance=rows.importance[mine].tolist(),
                importance_ess=rows.importance_ess[mine].tolist())
    statistics["island_gap"] = island_gap(statistics)
    return SMCRun(positions.astype(np.float32), logdensity.astype(np.float32), {"sampler": "smc", **asdict(config)},
                  statistics, Particles(rows, window))
