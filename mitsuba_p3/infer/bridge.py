"""From P3's posterior to NP3's: temper the neural term in, starting from P3's final particles.

NP3's likelihood is P3's colour likelihood times a neural term, so with P3's final particles
of an image (every run at lambda = 1 of the colour likelihood) the targets

    p(z | h) p_colour(I | z) p_neural(I | z)^lambda,   lambda from 0 to 1,

lead from P3's posterior to NP3's. In the tempering kernel's terms
(:mod:`mitsuba_p3.infer.tempering`) the tempered log likelihood is the neural term and the
"prior" is p(z | h) p_colour(I | z): the same steps (ESS-chosen increments, systematic
resampling, the moves of :mod:`mitsuba_p3.infer.smc_moves`) with one lambda for all rows,
because the observation carries the neural weight lambda w that the moves score with. Each
row's log evidence grows from P3's by the log mean of every increment's weights,
Z_NP3 = Z_P3 E_P3[p_neural]: with P3's run before them the steps make one SMC sampler from the
prior to NP3's posterior, as unbiased as a run from the prior, and far cheaper when the neural
term moves the posterior little, as on this project's data (a few nats beside colour terms of
hundreds: one or two increments).
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from . import tempering
from .smc_moves import kernels_for
from .smc_moves import mover


def bridge(core, observation, start, config, key, progress: Callable[[str, int, int], None] | None = None):
    """NP3's rows from P3's ``start`` rows (:class:`~mitsuba_p3.infer.smc.Rows`, on the window P3
    scored); ``core`` is NP3's. Returns the rows at NP3's posterior, their evidence NP3's."""
    import jax
    import jax.numpy as jnp

    from .smc import Rows, SMCState

    if core.config.kind != "np3":
        from ..errors import MitsubaP3Error

        raise MitsubaP3Error("the bridge tempers the neural term in: it needs the np3 likelihood's core")
    kernels = kernels_for(core, config)
    index = jnp.asarray(start.index, jnp.int32)
    weight = np.float32(core.config.neural_weight)
    weighted = lambda w: {**observation, "neural_weight": np.float32(w)}  # noqa: E731

    def split(z):
        """(neural term, log prior + colour term, log prior) of particles z: one render each."""
        colour, whole, logprior = (np.asarray(a, np.float64) for a in kernels.parts(jnp.asarray(z), index,
                                                                                     weighted(weight)))
        return whole - colour, logprior + colour, logprior

    def move(key, state: tempering.TemperedState):
        lam = float(state.tempering[0])
        logprior = np.asarray(kernels.prior(jnp.asarray(state.position), index), np.float64)
        colour = state.logprior - logprior
        at_lambda = state._replace(loglikelihood=(colour + lam * state.loglikelihood).astype(np.float32),
                                   logprior=logprior.astype(np.float32))
        sweeps = config.mcmc_steps + (config.final_steps if lam >= 1.0 else 0)
        moved, acceptance = mover(kernels, index, weighted(lam * weight), sweeps, config.material_every,
                                  np.ones(len(index)))(key, at_lambda)
        neural, base, _ = split(moved.position)
        return moved._replace(loglikelihood=neural.astype(np.float32), logprior=base.astype(np.float32)), acceptance

    neural, base, _ = split(start.state.position)
    state = tempering.init(start.state.position, neural, base, log_evidence=start.log_evidence)
    steps = []
    while state.tempering[0] < 1.0 and len(steps) < config.max_temperatures:
        key, k_step = jax.random.split(key)
        state, info = tempering.step(k_step, state, move, config.target_ess, shared=True,
                                     force=len(steps) + 1 == config.max_temperatures)
        steps.append(info)
        if progress:
            progress("bridge", int(100 * state.tempering[0]), 100)
    logprior = np.asarray(kernels.prior(jnp.asarray(state.position), index), np.float32)
    final = SMCState(state.position, (state.logprior - logprior + state.loglikelihood).astype(np.float32), logprior)
    # P3's two estimates of each run (:mod:`~mitsuba_p3.infer.importance`), each times the bridge's factor
    bridged = state.log_evidence - start.log_evidence
    shifted = lambda estimate: None if estimate is None else estimate + bridged  # noqa: E731
    return Rows(np.asarray(start.index), final, state.log_evidence, start.temperatures + len(steps),
                start.steps + [tempering.record(info, start.index) for info in steps], shifted(start.tempered),
                shifted(start.importance), start.importance_ess)
