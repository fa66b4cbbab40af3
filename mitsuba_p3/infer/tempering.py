"""Adaptive tempered SMC as a small kernel: one step is reweight, resample, move, adapt.

The state holds R independent runs ("rows") of N particles each. Row r targets

    pi_lambda(z) proportional to exp(logprior(z) + lambda_r loglikelihood(z)),

and the state caches every particle's ``loglikelihood`` and ``logprior``, so that a step
costs no render beyond its moves'. One :func:`step`:

1. **reweight**: choose each row's increment d lambda so that the incremental weights
   w = exp(d lambda loglikelihood) keep an effective sample size of ``target_ess`` N
   (bisection on the log ESS), and add log mean w to the row's running log evidence,
   an unbiased estimate of log Z_r once lambda_r = 1 (Del Moral et al. 2006);
2. **resample** systematically in proportion to w (to ``count`` particles: the first step
   of a run starts from more draws than it keeps);
3. **move** every particle with a pi_lambda-invariant kernel the caller gives, over all rows
   at once (so all rows share batched renders); a row already at lambda = 1 only moves;
4. **adapt** each row's walk ``scale`` towards 25% acceptance.

It is blackjax's ``adaptive_tempered_smc`` with three changes that are the reason this
project owns the loop: blackjax's tempered kernel evaluates every particle's log likelihood
again to weigh it and to choose the increment (here a render each, which the move has just
made), its state has one temperature where a batch
of rows needs one each, and its first step cannot start from importance-weighted draws (the
footprint start's ``offset``). What is blackjax's stays blackjax's: the log ESS and the
bisection (``blackjax.smc.ess.log_ess``, ``blackjax.smc.solver.dichotomy``, via
``ess_solver``) and systematic resampling (``blackjax.smc.resampling.systematic``).

The kernel knows nothing of scenes: hypotheses, footprint starts, islands and rounds
(:mod:`mitsuba_p3.infer.smc`) and the bridge from P3 to NP3 (:mod:`mitsuba_p3.infer.bridge`)
are layers that build the initial state and the move.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import numpy as np

# the walk's acceptance rate the scale adapts towards (Gelman et al.: about 0.23 in many dimensions)
TARGET_ACCEPTANCE = 0.25
# the gradient move's (MALA: about 0.57, Roberts and Rosenthal 1998)
TARGET_GRADIENT_ACCEPTANCE = 0.57
# the smallest increment a step takes, so a run always advances
MIN_INCREMENT = 1e-6


class TemperedState(NamedTuple):
    """R runs of N particles: positions (R, N, d), their cached log likelihoods and log priors
    (R, N), each row's temperature lambda and running log evidence (R,), its walk scale and its
    gradient move's step scale (R,)."""
    position: np.ndarray
    loglikelihood: np.ndarray
    logprior: np.ndarray
    tempering: np.ndarray
    log_evidence: np.ndarray
    scale: np.ndarray
    gradient_scale: np.ndarray


class TemperingInfo(NamedTuple):
    """What one step did, per row (R,): the log evidence it added, the incremental weights' ESS as a
    share of the particles, lambda after the step, and the acceptance of each move the caller ran
    (a dict of (R,) rates, e.g. ``walk`` and ``material``)."""
    log_evidence_increment: np.ndarray
    ess: np.ndarray
    tempering: np.ndarray
    acceptance: dict


# A move: (key, state resampled, at its temperatures) -> (state moved, {move name: (R,) acceptance}).
Move = Callable[[object, TemperedState], tuple[TemperedState, dict]]


def init(position, loglikelihood, logprior, log_evidence=None, tempering=None) -> TemperedState:
    """A state at lambda = 0 (or ``tempering``) with walk scale 1."""
    rows = np.shape(loglikelihood)[0]
    _check_finite(np.asarray(loglikelihood))
    zeros = np.zeros(rows)
    return TemperedState(np.asarray(position, np.float32), np.asarray(loglikelihood, np.float32),
                         np.asarray(logprior, np.float32), zeros if tempering is None else np.asarray(tempering, float),
                         zeros if log_evidence is None else np.asarray(log_evidence, np.float64), np.ones(rows),
                         np.ones(rows))


@functools.lru_cache(maxsize=None)
def _jitted():
    """The kernel's two jitted pieces, built on first use (JAX is imported lazily)."""
    import jax
    import jax.numpy as jnp
    from blackjax.smc.ess import ess_solver, log_ess
    from blackjax.smc.resampling import systematic
    from blackjax.smc.solver import dichotomy

    @functools.partial(jax.jit, static_argnames=("has_offset",))
    def solve(loglikelihood, remaining, target_ess, offset, has_offset: bool):
        """Per row the largest increment <= remaining whose weights d * loglikelihood (+ offset) keep
        ESS >= target_ess N; NaN (read as 0) for a row below target even at 0."""
        def one(ll, max_delta, off):
            if not has_offset:
                return ess_solver(lambda x: x, ll, target_ess, max_delta, dichotomy)
            target = jnp.log(ll.shape[0] * target_ess)
            return dichotomy(lambda d: log_ess(jnp.nan_to_num(d * ll + off)) - target, 0.0, max_delta)

        return jnp.nan_to_num(jax.vmap(one)(loglikelihood, remaining, offset), nan=0.0)

    @functools.partial(jax.jit, static_argnames=("count",))
    def draw(key, log_weights, count: int):
        weights = jax.nn.softmax(log_weights, axis=-1)
        keys = jax.random.split(key, log_weights.shape[0])
        return jax.vmap(lambda k, w: systematic(k, w, count))(keys, weights).astype(jnp.int32)

    return solve, draw


def increments(loglikelihood: np.ndarray, remaining: np.ndarray, target_ess: float, offset=None) -> np.ndarray:
    """(R, N) log likelihoods -> (R,) increments: for each row the largest d lambda <= ``remaining``
    whose incremental weights d lambda loglikelihood + ``offset`` (log importance weights, (R, N))
    keep an ESS of ``target_ess`` N; at least :data:`MIN_INCREMENT` where anything remains."""
    ll = np.where(np.isfinite(loglikelihood), loglikelihood, -1e30).astype(np.float32)
    remaining = np.asarray(remaining, np.float32)
    off = np.zeros_like(ll) if offset is None else np.asarray(offset, np.float32)
    solve, _ = _jitted()
    step = np.asarray(solve(ll, remaining, np.float32(target_ess), off, offset is not None), np.float64)
    return np.where(remaining > 0, np.clip(step, MIN_INCREMENT, remaining), 0.0)


def resample(key, log_weights: np.ndarray, count: int | None = None) -> np.ndarray:
    """(R, M) log weights -> (R, count) indices per row, systematic (blackjax), in proportion to
    the weights; ``count`` defaults to M."""
    log_weights = np.where(np.isfinite(log_weights), log_weights, -1e30)
    _, draw = _jitted()
    return np.asarray(draw(key, np.asarray(log_weights, np.float32), int(count or log_weights.shape[1])))


def reweight(key, state: TemperedState, target_ess: float, count: int | None = None, offset=None,
             force: bool = False, shared: bool = False) -> tuple[TemperedState, np.ndarray, np.ndarray]:
    """Steps 1 and 2 of :func:`step`: advance each row's lambda by its ESS-chosen increment (the whole
    remaining way with ``force``; the smallest row's for all rows with ``shared``), add the log mean
    incremental weight to its log evidence, resample ``count`` particles. Returns the new state, each
    row's increment and ESS share. ``offset`` (R, M): log importance weights of the particles
    (a first step from a proposal); they enter the weights and the evidence."""
    import jax

    remaining = 1.0 - state.tempering
    step = remaining if force else increments(state.loglikelihood, remaining, target_ess, offset)
    if shared:
        step = np.full_like(step, step.min())
    ll = np.where(np.isfinite(state.loglikelihood), state.loglikelihood, -1e30).astype(np.float64)
    log_w = step[:, None] * ll + (0.0 if offset is None else np.asarray(offset, np.float64))
    increment = np.logaddexp.reduce(log_w, axis=1) - np.log(log_w.shape[1])
    ess = np.exp(2 * np.logaddexp.reduce(log_w, axis=1) - np.logaddexp.reduce(2 * log_w, axis=1)) / log_w.shape[1]
    tempering = np.where(remaining - step < 1e-9, 1.0, state.tempering + step)
    chosen = resample(jax.random.fold_in(key, 0), log_w, count)
    if count is None:           # a row that did not advance (already at lambda = 1) keeps its particles as they are
        chosen = np.where((step > 0)[:, None], chosen, np.arange(chosen.shape[1])[None])
    take = lambda a: np.take_along_axis(a, chosen.reshape(chosen.shape + (1,) * (a.ndim - 2)), axis=1)  # noqa: E731
    new = state._replace(position=take(state.position), loglikelihood=take(state.loglikelihood),
                         logprior=take(state.logprior), tempering=tempering,
                         log_evidence=state.log_evidence + increment)
    return new, increment, ess


def step(key, state: TemperedState, move: Move, target_ess: float, count: int | None = None, offset=None,
         force: bool = False, shared: bool = False) -> tuple[TemperedState, TemperingInfo]:
    """One SMC step (the module docstring): reweight and resample (:func:`reweight`), ``move``
    every row at its new temperature, adapt the walk scales by the ``walk`` acceptance."""
    import jax

    k_reweight, k_move = jax.random.split(key)
    state, increment, ess = reweight(k_reweight, state, target_ess, count, offset, force, shared)
    state, acceptance = move(k_move, state)
    _check_finite(state.loglikelihood)
    return _adapt(state, acceptance), TemperingInfo(increment, ess, state.tempering.copy(), acceptance)


def _check_finite(loglikelihood) -> None:
    """A NaN log likelihood (a render that broke) poisons every weight and the increment's bisection,
    and a run would silently jump to lambda = 1 with a meaningless evidence: refuse it instead."""
    if np.isnan(loglikelihood).any():
        from ..errors import InferenceError

        rows = sorted({int(r) for r in np.argwhere(np.isnan(loglikelihood))[:, 0]})
        raise InferenceError(f"the log likelihood is NaN for some particles (rows {rows}): a render produced "
                             "non-finite values; this is a bug in the renderer or the model, please report it")


def _adapt(state: TemperedState, acceptance: dict) -> TemperedState:
    """Step 4: each row's walk scale towards :data:`TARGET_ACCEPTANCE` by its ``walk`` acceptance, and
    its gradient move's own scale (relative to the walk's) towards :data:`TARGET_GRADIENT_ACCEPTANCE` by
    the ``gradient`` acceptance (each by at most a factor 2 per step)."""
    if acceptance.get("walk") is not None:
        state = state._replace(scale=state.scale * adaptation(acceptance["walk"], TARGET_ACCEPTANCE))
    if acceptance.get("gradient") is not None:
        state = state._replace(gradient_scale=state.gradient_scale
                               * adaptation(acceptance["gradient"], TARGET_GRADIENT_ACCEPTANCE))
    return state


def adaptation(rate, target: float) -> np.ndarray:
    """The factor a move's scale changes by after an acceptance ``rate`` (per row): exp(2 (rate - target)),
    at most a factor 2 either way."""
    return np.clip(np.exp(2.0 * (np.asarray(rate, np.float64) - target)), 0.5, 2.0)


def record(info: TemperingInfo, index) -> dict:
    """One step's info as plain lists (for a posterior's statistics): per row its hypothesis index,
    lambda after the step, ESS share, log evidence increment and each move's acceptance."""
    return {"rows": [int(i) for i in index], "tempering": np.round(info.tempering, 6).tolist(),
            "ess": np.round(info.ess, 4).tolist(),
            "log_evidence_increment": np.round(info.log_evidence_increment, 4).tolist(),
            **{f"{name}_acceptance": np.round(np.asarray(rate, float), 4).tolist()
               for name, rate in info.acceptance.items()}}


# ---------------------------------------------------------------- persistent sampling
class Pool(NamedTuple):
    """Persistent sampling's ensemble (Karamanis et al. 2025): every row's particles after each step's
    move, (R, K, N, d) positions and (R, K, N) cached log likelihoods and log priors for K slots, each
    slot's lambda and log evidence (R, K), and how many slots are filled."""
    position: np.ndarray
    loglikelihood: np.ndarray
    logprior: np.ndarray
    tempering: np.ndarray
    log_evidence: np.ndarray
    filled: int


def pool_add(pool: Pool | None, state: TemperedState, capacity: int) -> Pool:
    """The pool with ``state``'s particles as its next slot (a new pool of ``capacity`` slots if None;
    a full pool drops its oldest slot)."""
    if pool is None:
        rows, n = state.loglikelihood.shape
        pool = Pool(np.zeros((rows, capacity, n) + state.position.shape[2:], np.float32),
                    np.zeros((rows, capacity, n), np.float32), np.zeros((rows, capacity, n), np.float32),
                    np.zeros((rows, capacity)), np.zeros((rows, capacity)), 0)
    if pool.filled == pool.position.shape[1]:
        pool = Pool(*(np.roll(a, -1, axis=1) for a in pool[:5]), pool.filled - 1)
    slot = pool.filled
    arrays = [a.copy() for a in pool[:5]]
    for array, value in zip(arrays, (state.position, state.loglikelihood, state.logprior, state.tempering,
                                     state.log_evidence)):
        array[:, slot] = value
    return Pool(*arrays, slot + 1)


@functools.lru_cache(maxsize=None)
def _persistent_jitted():
    """Per row: the persistent weights of every pooled particle for a candidate lambda, with their ESS
    and log evidence (blackjax's equations 14-17), and the increment that keeps a target ESS."""
    import jax
    import jax.numpy as jnp
    from blackjax.smc.persistent_sampling import compute_log_persistent_weights, compute_persistent_ess
    from blackjax.smc.solver import dichotomy

    def weights(loglikelihood, log_evidence, schedule, filled, lam):
        # slot `filled` holds the candidate lambda; the slots before it form the mixture
        schedule = schedule.at[filled].set(lam)
        log_w, log_z = compute_log_persistent_weights(loglikelihood, log_evidence, schedule, filled,
                                                      normalize_to_one=True)
        return log_w, log_z, compute_persistent_ess(log_w)

    @jax.jit
    def solve(loglikelihood, log_evidence, schedule, filled, current, remaining, target):
        def one(ll, log_z, lam_s, lam, rest):
            def fun(delta):
                return jnp.log(weights(ll, log_z, lam_s, filled, lam + delta)[2]) - jnp.log(target)
            return jnp.where(rest > 0, jnp.nan_to_num(dichotomy(fun, 0.0, rest), nan=0.0), 0.0)
        return jax.vmap(one)(loglikelihood, log_evidence, schedule, current, remaining)

    @jax.jit
    def evaluate(loglikelihood, log_evidence, schedule, filled, lam):
        return jax.vmap(lambda ll, z, s, l: weights(ll, z, s, filled, l))(loglikelihood, log_evidence, schedule, lam)

    return solve, evaluate


def persistent_reweight(key, state: TemperedState, pool: Pool, target_ess: float, force: bool = False,
                        shared: bool = False) -> tuple[TemperedState, np.ndarray, np.ndarray]:
    """:func:`reweight` for persistent sampling: the next lambda keeps the ESS of the *whole pool's*
    weights at ``target_ess`` N (it can exceed N), each row's log evidence is the pool's estimate at the
    new lambda (eq. 16), and N particles are resampled from the pool (systematic). The pool mixes every
    past step's particles, so a region an earlier step's particles covered can be resampled again at
    a later temperature, where plain SMC has lost it."""
    solve, evaluate = _persistent_jitted()
    rows, slots, n = pool.loglikelihood.shape
    ll = np.where(np.isfinite(pool.loglikelihood), pool.loglikelihood, -1e30).astype(np.float32)
    # padded slots after `filled` hold zeros, as blackjax's padded state does; one slot more for the candidate
    pad = lambda a: np.concatenate([a, np.zeros(a.shape[:1] + (1,) + a.shape[2:], a.dtype)], 1)  # noqa: E731
    ll, log_z, schedule = pad(ll), pad(pool.log_evidence.astype(np.float32)), pad(pool.tempering.astype(np.float32))
    remaining = 1.0 - state.tempering
    step = remaining if force else np.asarray(solve(ll, log_z, schedule, pool.filled,
                                                    state.tempering.astype(np.float32), remaining.astype(np.float32),
                                                    np.float32(target_ess * n)), float)
    step = np.where(remaining > 0, np.clip(step, MIN_INCREMENT, remaining), 0.0)
    if shared:
        step = np.full_like(step, step.min())
    tempering = np.where(remaining - step < 1e-9, 1.0, state.tempering + step)
    log_w, new_log_z, ess = (np.asarray(a, np.float64) for a in evaluate(ll, log_z, schedule, pool.filled,
                                                                        tempering.astype(np.float32)))
    flat = log_w[:, :pool.filled].reshape(rows, -1)
    chosen = resample(key, flat, n)
    take = lambda a: np.take_along_axis(a[:, :pool.filled].reshape((rows, -1) + a.shape[3:]),  # noqa: E731
                                        chosen.reshape(chosen.shape + (1,) * (a.ndim - 3)), axis=1)
    new = state._replace(position=take(pool.position), loglikelihood=take(pool.loglikelihood),
                         logprior=take(pool.logprior), tempering=tempering, log_evidence=new_log_z)
    return new, new_log_z - state.log_evidence, ess / n


def persistent_step(key, state: TemperedState, pool: Pool, move: Move, target_ess: float, force: bool = False,
                    shared: bool = False) -> tuple[TemperedState, Pool, TemperingInfo]:
    """One persistent-sampling step: reweight the pool and resample from it
    (:func:`persistent_reweight`), move, adapt, and add the moved particles to the pool."""
    import jax

    k_reweight, k_move = jax.random.split(key)
    state, increment, ess = persistent_reweight(k_reweight, state, pool, target_ess, force, shared)
    state, acceptance = move(k_move, state)
    state = _adapt(state, acceptance)
    return state, pool_add(pool, state, pool.position.shape[1]), \
        TemperingInfo(increment, ess, state.tempering.copy(), acceptance)
