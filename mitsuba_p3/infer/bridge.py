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

The same steps bring in the image's own noise scale (``term="scale_weight"``; ``--noise scaled``,
:mod:`mitsuba_p3.fit.fields`, "An image's own scale"): the SMC searches under the fixed-scale density
p_1 and the bridge then tempers log p - log p_1 in, so that the search keeps the fixed scale's long
ladder of temperatures (the scale's density is flat far from the object, where the walk finds it) and
the evidence is the scaled density's.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from . import tempering
from .smc_moves import kernels_for
from .smc_moves import mover

# how the image's own noise scale enters a run: bridged in after the search under the fixed scale. Records of
# cached posteriors (an evaluation's run.json, an SBC cache's tag) name it, so that those of its first form
# (tempered in from the prior) are refused rather than resumed
SCALE_FORM = "bridged"


def bridge(core, observation, start, config, key, progress: Callable[[str, int, int], None] | None = None,
           term: str = "neural_weight"):
    """The rows at ``core``'s posterior from ``start`` rows (:class:`~mitsuba_p3.infer.smc.Rows`, on the
    window they scored) at its posterior without ``term``: NP3's from P3's (``neural_weight``; ``core`` is
    NP3's), or the image's own noise scale's from the fixed scale's (``scale_weight``; ``core``'s likelihood
    has a scale). Their evidence is ``core``'s."""
    import jax
    import jax.numpy as jnp

    from ..errors import MitsubaP3Error
    from .smc import Rows, SMCState

    if term == "neural_weight":
        if core.config.kind != "np3":
            raise MitsubaP3Error("the bridge tempers the neural term in: it needs the np3 likelihood's core")
        weight = np.float32(core.config.neural_weight)
    elif term == "scale_weight":
        if core.config.scale is None:
            raise MitsubaP3Error("the scale's bridge needs a likelihood with the image's own noise scale")
        weight = np.float32(1.0)
    else:
        raise MitsubaP3Error(f"the bridge tempers in neural_weight or scale_weight; got {term!r}")
    kernels = kernels_for(core, config)
    index = jnp.asarray(start.index, jnp.int32)
    weighted = lambda w: {**observation, term: np.float32(w)}  # noqa: E731

    def split(z):
        """(the term, log prior + the rest of the log likelihood, log prior) of particles z: one render each."""
        rest, whole, logprior = (np.asarray(a, np.float64) for a in kernels.parts(jnp.asarray(z), index,
                                                                                  weighted(weight), term=term))
        return whole - rest, logprior + rest, logprior

    def move(key, state: tempering.TemperedState):
        lam = float(state.tempering[0])
        logprior = np.asarray(kernels.prior(jnp.asarray(state.position), index), np.float64)
        rest = state.logprior - logprior
        at_lambda = state._replace(loglikelihood=(rest + lam * state.loglikelihood).astype(np.float32),
                                   logprior=logprior.astype(np.float32))
        sweeps = config.mcmc_steps + (config.final_steps if lam >= 1.0 else 0)
        moved, acceptance = mover(kernels, index, weighted(lam * weight), sweeps, config.material_every,
                                  np.ones(len(index)))(key, at_lambda)
        tempered, base, _ = split(moved.position)
        return moved._replace(loglikelihood=tempered.astype(np.float32), logprior=base.astype(np.float32)), acceptance

    tempered, base, _ = split(start.state.position)
    state = tempering.init(start.state.position, tempered, base, log_evidence=start.log_evidence)
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
