"""The tempered SMC's settings (:class:`SMCConfig`), and the defaults they had before they changed.

Every field is a knob of :func:`mitsuba_p3.infer.smc.sample_smc`; the comment beside a field says what
it does; a default that was chosen was chosen on train classes. ``mitsuba-p3 ... --set smc.FIELD=VALUE`` sets any of them
(:mod:`mitsuba_p3.cli.settings`). :data:`DEFAULTS_BEFORE` lets a record written before a default
changed (an evaluation's ``run.json``, an SBC cache's tag) be read with the values it was made with.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fit.noise import SCORING_WINDOW
from .smc_moves import SYMMETRY_MOVES


# Settings whose default changed after they were added, at the value they had before: a record (an
# evaluation's run.json, an SBC cache's tag) that does not name them was made with these values
DEFAULTS_BEFORE = {"wide": 1, "wide_steps": 0, "coarse": 1, "symmetry": "free", "chart": False, "inside_window": False,
                   "rounds": 1, "importance": 0}


@dataclass(frozen=True)
class SMCConfig:
    particles: int = 64            # per hypothesis and run
    oversample: int = 8            # prior draws per particle at the start (the first reweighting picks N of them)
    mcmc_steps: int = 5            # random-walk sweeps per temperature
    material_every: int = 5        # a material update after every k-th sweep (and the last)
    final_steps: int = 6           # extra sweeps at lambda = 1, to spread the resampled particles again
    # MALA sweeps over the pose after the walks, at every temperature and (final_) once at lambda = 1: a
    # gradient-informed move with finite-difference likelihood gradients (k renders per particle each)
    gradient_steps: int = 0
    final_gradient_steps: int = 0
    # a wide start: the first wide_steps temperatures keep wide x particles (resampled from the oversampled
    # draws, so at most oversample x), the step after them resamples down to particles: width where the pose
    # is chosen
    wide: int = 4
    wide_steps: int = 6
    # the wide start scored at 1 / coarse of the resolution (2: a quarter of the pixels, so wide = 4 costs
    # about what full-resolution first steps cost; 1: at the full resolution); the step after it reweights
    # to the full likelihood. Chosen on fsclvr's and room's train images (the runs of a hypothesis agree better
    # for a little more time)
    coarse: int = 2
    footprint: bool = True         # half of the first step's draws placed from the image's footprint
    kinds: bool = False            # material kinds as hypotheses of their own (else within each shape)
    ridge: int = 3                 # ridge moves (colour x s, weights / s; no render) after every walk
    # the symmetry move (turns of 90 and 180 degrees): "rendered" at every material update (exact), or "free"
    # after every walk without a render (the likelihood taken as unchanged, which a row of outline pixels
    # breaks for about a tenth of the turns)
    symmetry: str = "rendered"
    # the walk in each particle's symmetry chart (:mod:`mitsuba_p3.infer.symmetry`): its covariance one
    # symmetric copy's width, not the distance between the copies the symmetry move spreads particles over
    # (False: the walk in z with the covariance of all copies)
    chart: bool = True
    # every material update starts with the material kind's jump: a shininess from its prior and the weights
    # from their conditional there, one more render (:meth:`~mitsuba_p3.infer.model.PosteriorCore._kind_jump`)
    jump: bool = False
    # a scene whose object's centre lies outside the scoring window has likelihood 0 (the window's assumption,
    # :mod:`mitsuba_p3.infer.window`); False scores it by the window alone, where
    # the bare floor it shows beats every scene a little off the object
    inside_window: bool = True
    islands: int = 2               # independent SMC runs per hypothesis and round, their evidence pooled
    rounds: int = 2                # rounds of runs; a round after the first runs only the contenders
    decided: float = 0.99          # no further round once the leader has this weight, even at its worst run's estimate
    # score only a (height, width) window around the footprint (None: the whole image)
    window: tuple | None = SCORING_WINDOW
    target_ess: float = 0.5        # of the incremental weights, as a share of the particles
    max_temperatures: int = 100    # a run that needs more jumps to lambda = 1 (statistics: 'forced')
    draws: int = 400               # posterior draws returned (resampled from the mixture)
    # persistent sampling (Karamanis et al. 2025): after the first step, each step reweights and resamples
    # the pool of every earlier step's particles, choosing lambda so that the pool's ESS is persistent_ess N
    persistent: bool = False
    persistent_ess: float = 1.0
    # waste-free SMC (Dau and Chopin 2022), P > 1: each step resamples N / P particles and keeps every state
    # of P - 1 sweeps from each (mcmc_steps and final_steps then unused)
    waste_free: int = 0
    # each run's evidence also estimated by importance sampling from a Student-t fitted to its final particles
    # (this many draws, one render each), the run keeping the mean of both estimates (:mod:`~mitsuba_p3.infer.
    # importance`); 0: the tempered estimate alone
    importance: int = 256
    # NP3 only: start from P3's final particles and temper the neural term in (:func:`bridge`),
    # rather than temper all of NP3's likelihood in from the prior
    bridge: bool = True
    seed: int = 0

    def __post_init__(self):
        from ..errors import ConfigError, check_counts

        check_counts(self, {"particles": 4, "oversample": 1, "mcmc_steps": 1, "material_every": 1, "final_steps": 0,
                            "gradient_steps": 0, "final_gradient_steps": 0, "islands": 1, "rounds": 1,
                            "max_temperatures": 1, "draws": 4, "seed": 0, "ridge": 0, "waste_free": 0, "wide": 1,
                            "wide_steps": 0, "coarse": 1, "importance": 0}, "smc ")
        if self.wide_steps and self.wide > 1 and (self.persistent or self.waste_free > 1):
            raise ConfigError("smc wide start excludes persistent sampling and waste-free SMC (with them, set "
                              "smc.wide_steps=0)")
        if self.symmetry not in SYMMETRY_MOVES:
            raise ConfigError(f"smc symmetry must be one of {', '.join(SYMMETRY_MOVES)}; got {self.symmetry!r}")
        if not 0.0 < self.target_ess < 1.0:
            raise ConfigError(f"smc target-ess must lie in (0, 1); got {self.target_ess}")
        if self.waste_free > 1 and (self.particles % self.waste_free or self.persistent):
            raise ConfigError(f"smc waste-free P must divide the particles ({self.particles}) and excludes persistent "
                              f"sampling; got P = {self.waste_free}")
        if not 0.0 < self.persistent_ess <= self.max_temperatures:
            raise ConfigError(f"smc persistent-ess must lie in (0, max-temperatures]; got {self.persistent_ess}")
        if not 0.0 < self.decided <= 1.0:
            raise ConfigError(f"smc decided must lie in (0, 1]; got {self.decided}")
        if self.window is not None:
            window = tuple(self.window)
            if len(window) != 2 or not all(isinstance(v, (int, np.integer)) and v >= 8 for v in window):
                raise ConfigError(f"smc window must be (height, width) in pixels, each at least 8; got {self.window}")
            object.__setattr__(self, "window", tuple(int(v) for v in window))
