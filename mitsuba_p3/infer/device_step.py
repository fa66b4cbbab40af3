"""One tempered SMC step as one compiled call, on the device where the particles are.

:func:`mitsuba_p3.infer.tempering.step` is the kernel as the host sees it: it solves each row's
increment and resamples in two small compiled calls, gathers the particles and computes each row's
walk chart and covariance factor with numpy, and calls the move's compiled sweeps
(:mod:`mitsuba_p3.infer.smc_moves`) with them. Each of those pieces copies between the host and
JAX's device, and each copy waits for the device to finish. On a CPU that wait is nothing; on a
GPU the SMC's per-step work was a loop of small launches and copies, and the device waited on
the host.

Here the same step is one jitted function of the particles, which never leave the device:

1. **reweight**: each row's increment by blackjax's ESS solver (the kernel's own ``solve``), its
   incremental weights, their ESS and log mean;
2. **resample** systematically (the kernel's own ``draw``, with the key the host step folds);
   a row already at lambda = 1 keeps its particles;
3. **move**: each row's chart centre and walk factor from its resampled particles
   (:mod:`~mitsuba_p3.infer.symmetry`, :mod:`~mitsuba_p3.infer.move_scales`), then the move's sweeps
   (``Kernels.sweeps``), the final sweeps included where every row has reached lambda = 1.

The host reads back only what it keeps per step: each row's increment, the log mean's two parts
(so the running log evidence adds in float64, as the host step's does), the ESS, the acceptance
rates and a NaN flag, in one transfer; it adapts the walk scales as the host step does
(:func:`mitsuba_p3.infer.tempering.adaptation`). The keys split as the host step splits them, so the
two steps draw alike up to float32 rounding (the host factors the covariance in float64).

It serves the plain steps of :func:`mitsuba_p3.infer.smc.temper`: not the first (from more draws, with
the footprint start's weights), not the change from a coarse start, not persistent sampling,
waste-free SMC or MALA, which the host step runs. :func:`step_for` chooses it where JAX runs on a
GPU; ``MITSUBA_P3_SMC_STEP`` forces either.
"""
from __future__ import annotations

import functools

import numpy as np

from .move_scales import walk_factors
from .symmetry import chart_centres, folded
from .tempering import MIN_INCREMENT, TemperedState, TemperingInfo, _adapt, _check_finite, _jitted

STEP_ENV = "MITSUBA_P3_SMC_STEP"
STEPS = ("device", "host")


def step_for(platform: str | None = None) -> str:
    """Where a plain SMC step runs: ``device`` (one compiled call, :func:`step`) where JAX runs on a GPU,
    ``host`` (:func:`mitsuba_p3.infer.tempering.step`) on a CPU, where a copy to the host is a memcpy in
    the same memory; ``MITSUBA_P3_SMC_STEP`` forces either."""
    from ..backend import follow_device
    from ..errors import ConfigError

    return follow_device(STEP_ENV, STEPS, "device", "host", ConfigError, platform)


@functools.lru_cache(maxsize=8)
def _compiled(kernels, sweeps: int, final_sweeps: int, material_every: int):
    """The jitted step for one core's kernels and one move's sweep counts (cached: a core serves every
    image of a data set)."""
    import jax
    import jax.numpy as jnp

    solve, draw = _jitted()

    @jax.jit
    def run(key, particles, remaining, tempering, scale, target_ess, force, index, observation):
        position, loglik, logprior = particles
        rows, n = loglik.shape
        k_reweight, k_move = jax.random.split(key)
        # 1. reweight: tempering.reweight's arithmetic, in float32 on the device
        ll = jnp.where(jnp.isfinite(loglik), loglik, -1e30)
        solved = solve(ll, remaining, target_ess, jnp.zeros_like(ll), False)
        step = jnp.where(force, remaining, solved)
        step = jnp.where(remaining > 0, jnp.clip(step, MIN_INCREMENT, remaining), 0.0)
        top = ll.max(axis=1)
        log_w = step[:, None] * (ll - top[:, None])                 # the weights' log, less each row's max
        lse = jax.nn.logsumexp(log_w, axis=1)
        ess = jnp.exp(2 * lse - jax.nn.logsumexp(2 * log_w, axis=1)) / n
        lam = jnp.where(remaining - step < 1e-9, 1.0, tempering + step)
        # 2. resample; a row that did not advance keeps its particles
        chosen = draw(jax.random.fold_in(k_reweight, 0), log_w, n)
        chosen = jnp.where((step > 0)[:, None], chosen, jnp.arange(n)[None])
        position, loglik, logprior = (jnp.take_along_axis(a, chosen.reshape(chosen.shape + (1,) * (a.ndim - 2)), 1)
                                      for a in (position, loglik, logprior))
        # 3. move: the chart and the walk's factor from the resampled particles, then the sweeps
        centres = chart_centres(position, jnp)
        tril = walk_factors(folded(position, centres, jnp) if kernels.chart else position, scale, jnp)
        total = sweeps + final_sweeps * jnp.all(lam >= 1.0).astype(jnp.int32)
        _, moved, *rates = kernels.sweeps(k_move, (position, loglik, logprior), index, lam, tril, centres,
                                          observation, total, material_every=material_every)
        small = {"step": step, "top": top, "lse": lse, "ess": ess, "nan": jnp.isnan(moved[1]).any(axis=1),
                 **dict(zip(("walk", "material", "turn", "jump"), rates))}
        return moved, small

    return run


def on_host(state: TemperedState) -> TemperedState:
    """The state with its particles as numpy arrays (as the host step and the SMC's results take them)."""
    return state._replace(position=np.asarray(state.position), loglikelihood=np.asarray(state.loglikelihood),
                          logprior=np.asarray(state.logprior))


def step(key, state: TemperedState, kernels, index, observation, sweeps: int, material_every: int,
         final_sweeps: int, target_ess: float, force: bool = False) -> tuple[TemperedState, TemperingInfo]:
    """:func:`mitsuba_p3.infer.tempering.step` with :func:`~mitsuba_p3.infer.smc_moves.mover`'s walks and
    material updates as the move (``sweeps``, ``material_every``, ``final_sweeps`` once every row is at
    lambda = 1), in one compiled call (the module docstring). The state's particles stay JAX arrays on
    the device; its per-row temperatures, evidence and scales come back as numpy, as the host step's."""
    import jax
    import jax.numpy as jnp

    run = _compiled(kernels, int(sweeps), int(final_sweeps), int(material_every))
    remaining = 1.0 - state.tempering
    moved, small = run(key, tuple(jnp.asarray(a) for a in state[:3]), jnp.asarray(remaining, jnp.float32),
                       jnp.asarray(state.tempering, jnp.float32), jnp.asarray(state.scale, jnp.float32),
                       jnp.float32(target_ess), jnp.bool_(force), index, observation)
    small = jax.device_get(small)                                   # the step's one wait for the device
    step_ = np.asarray(small["step"], np.float64)
    n = state.loglikelihood.shape[1]
    increment = step_ * small["top"].astype(np.float64) + small["lse"] - np.log(n)
    tempering = np.where(remaining - step_ < 1e-9, 1.0, state.tempering + step_)
    if small["nan"].any():      # refused as the host step refuses it, naming the rows
        _check_finite(np.where(small["nan"][:, None], np.nan, 0.0))
    rates = {name: np.asarray(small[name]) for name in ("walk", "material", "turn", "jump")
             if not np.isnan(small[name]).all()}
    new = state._replace(position=moved[0], loglikelihood=moved[1], logprior=moved[2], tempering=tempering,
                         log_evidence=state.log_evidence + increment)
    return _adapt(new, rates), TemperingInfo(increment, np.asarray(small["ess"], np.float64), tempering.copy(),
                                             rates)
