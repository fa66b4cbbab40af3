"""The moves of an SMC run: every particle of every row, in one batched render per move.

A sweep is a Gaussian random walk over position, yaw and size (the dimensions of
:data:`WALK_MASK`; each row's covariance 2.38^2 / d times its own particles', times the
row's adapted ``scale``), made in the row's symmetry chart (:mod:`mitsuba_p3.infer.symmetry`:
the particles' four equivalent copies folded onto one, so that the covariance is one copy's
width, not the distance between copies), then ``ridge`` moves along the colour/weight ridge (no render);
every ``material_every``-th sweep and the last end with the symmetry move (the object turned
by 90 or 180 degrees, rendered: one render) and the material Metropolis-within-Gibbs update
(one render of the material bases; the costliest move). With
``gradient_steps`` (``final_gradient_steps`` at lambda = 1) preconditioned MALA sweeps over the
pose follow: Langevin proposals along the particles' covariance, the likelihood's gradient a
forward difference (one render per pose dimension; a render's own gradient has no silhouette
term), the drift truncated (MALTA). All are MH moves that leave each row's tempered target
p(z | h) p(I | z)^lambda invariant.
Five walks per material update, and the ridge moves (along the colour/weight ridge the material
update crawls along), were chosen on train images.

:func:`kernels` jits them once per posterior core, and a move's sweeps as one call (a loop on the
device, not one call per sweep from the host); :func:`mover` makes the
:data:`~mitsuba_p3.infer.tempering.Move` a tempering step calls.
"""
from __future__ import annotations

import functools
from typing import Callable, NamedTuple

import numpy as np

from .. import small_linalg
from ..space import SLICES
from .chunks import map_in_chunks
from .hypotheses import hypotheses_of, hypothesis_log_prior
from .move_scales import POSE_MASK, WALK_MASK, gradient_step, pose_directions, walk_factors
from .symmetry import chart_centres, folded, quarter_turn, quarters
from .tempering import TARGET_GRADIENT_ACCEPTANCE, TemperedState, adaptation

# where the symmetry move's turns are made: rendered at every material update (exact), or free after
# every walk (no render; the likelihood taken as unchanged)
SYMMETRY_MOVES = ("rendered", "free")
# the gradient move's finite-difference step along each direction, in units of the particles' spread
# along it: a secant over a tenth of the posterior's width, so silhouette edges, which a render's
# gradient without a boundary term misses, still pull
GRADIENT_STEP = 0.1
# the largest drift of a gradient move, in units of its step's noise (a truncated drift, MALTA)
DRIFT_LIMIT = 3.0


class Kernels(NamedTuple):
    """The jitted functions of one core's SMC (see :func:`_kernels`)."""
    score: Callable
    walk: Callable
    material: Callable
    parts: Callable
    prior: Callable
    gradient: Callable
    turn: Callable
    chart: bool          # the walk moves in each particle's symmetry chart (else plainly in z)
    sweeps: Callable     # a move's walks and material updates in one call


@functools.lru_cache(maxsize=4)
def _kernels(core, walk_mask: tuple, kinds: bool, ridge: int, symmetry: str, chart: bool, jump: bool) -> Kernels:
    """Jitted kernels for one :class:`PosteriorCore`: scores of all particles, the two moves of all
    particles at per-row temperatures, and (for the bridge) the colour and whole log likelihood of
    all particles from one render each. Every row is one run of one hypothesis; ``index`` (R,) names
    each row's hypothesis (a row of :func:`hypotheses_of` without islands). ``symmetry``: "rendered"
    turns the object (:meth:`~mitsuba_p3.infer.model.PosteriorCore.symmetry_turn`) at the start of
    every material update and renders the turn (exact); "free" turns it after every walk without a
    render (the likelihood taken as unchanged, true only up to the outline's rasterisation). ``chart``:
    the walk moves in each particle's symmetry chart (:mod:`mitsuba_p3.infer.symmetry`), else in z.
    ``jump``: every material update starts with the material kind's jump
    (:meth:`~mitsuba_p3.infer.model.PosteriorCore.scored_material_move`; one more render)."""
    import jax
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import RWState

    log_prior = hypothesis_log_prior(core.prior, hypotheses_of(core.prior, kinds))
    mask = jnp.asarray(walk_mask, jnp.float32)

    def loglik_all(z, observation):                               # (R, N, d) -> (R, N)
        return core.log_likelihoods(z.reshape(-1, z.shape[-1]), observation).reshape(z.shape[:2])

    def logprior_all(z, index):
        h = jnp.broadcast_to(index[:, None], z.shape[:2])
        return jax.vmap(jax.vmap(log_prior))(z, h)

    @jax.jit
    def score(z, index, observation):
        return loglik_all(z, observation), logprior_all(z, index)

    @functools.partial(jax.jit, static_argnames="term")
    def parts(z, index, observation, term="neural_weight"):
        colour, whole = core.log_likelihoods(z.reshape(-1, z.shape[-1]), observation, parts=term)
        return colour.reshape(z.shape[:2]), whole.reshape(z.shape[:2]), logprior_all(z, index)

    @jax.jit
    def walk(key, state, index, tempering, tril, centres, observation):
        """The random walk in each particle's symmetry chart (:mod:`mitsuba_p3.infer.symmetry`: turned
        into the copy within 45 degrees of its row's ``centres``, walked, turned back), then the free
        symmetry move (where chosen) and the ridge moves; returns (state, walk acceptance (R,))."""
        k_walk, k_accept, k_symmetry = jax.random.split(key, 3)
        z, loglik, logprior = state
        copy = quarters(z, centres, jnp) if chart else jnp.zeros(z.shape[:2], jnp.int32)
        folded_z, log_unturn = quarter_turn(z, -copy, jnp)                  # log |du/dz| at z
        noise = jax.random.normal(k_walk, z.shape) * mask
        proposed, log_turn = quarter_turn(folded_z + jnp.einsum("hij,hnj->hni", tril, noise), copy, jnp)
        # the proposal's density each way (the Hastings term): forward N(noise) |du'/dz'|, reverse the walk
        # from z' in z' 's own chart; where a step crosses into another copy the two charts differ
        back = quarters(proposed, centres, jnp) if chart else copy
        from_new, _ = quarter_turn(proposed, -back, jnp)
        to_old, log_unturn_back = quarter_turn(z, -back, jnp)
        # the reverse step's noise, L^-1 (z - z'): no LAPACK call (mitsuba_p3/small_linalg.py)
        reverse = small_linalg.forward((tril + jnp.diag(1.0 - mask))[:, None], to_old - from_new, jnp)
        crossed = (back - copy) % 4 != 0
        log_hastings = jnp.where(crossed, 0.5 * jnp.sum(noise ** 2 - reverse ** 2, axis=-1) + log_unturn_back,
                                 log_unturn) + log_turn
        new_loglik, new_logprior = loglik_all(proposed, observation), logprior_all(proposed, index)
        log_ratio = (new_logprior + tempering[:, None] * new_loglik - logprior - tempering[:, None] * loglik
                     + log_hastings)
        accept = jnp.log(jax.random.uniform(k_accept, loglik.shape)) < log_ratio
        z = jnp.where(accept[..., None], proposed, z)
        loglik, logprior = jnp.where(accept, new_loglik, loglik), jnp.where(accept, new_logprior, logprior)
        turned = RWState(z.reshape(-1, z.shape[-1]), logprior.reshape(-1))
        if symmetry == "free":   # no render; the tempered density changes only through the yaw prior
            turned = jax.vmap(core.symmetry_move)(jax.random.split(k_symmetry, turned.position.shape[0]), turned)
        if ridge:
            # along the colour/weight ridge: no render; the density changes by the hypothesis prior's difference
            h = jnp.repeat(index, z.shape[1])
            for k_ridge in jax.random.split(jax.random.fold_in(k_symmetry, 1), ridge):
                turned = jax.vmap(lambda key, state, row: core.ridge_move(key, state, lambda p: log_prior(p, row)))(
                    jax.random.split(k_ridge, turned.position.shape[0]), turned, h)
        return (turned.position.reshape(z.shape), loglik, turned.logdensity.reshape(logprior.shape)), \
            accept.mean(axis=1)

    def turn(key, state, index, tempering, observation):
        """The symmetry move, rendered: every particle turned by 90, 180 or -90 degrees and accepted
        with the tempered density's ratio and the turn's Jacobian (one render per particle).
        Returns (state, each row's acceptance (R,))."""
        k_turn, k_accept = jax.random.split(key)
        z, loglik, logprior = state
        flat = z.reshape(-1, z.shape[-1])
        proposed, log_jacobian = jax.vmap(core.symmetry_turn)(jax.random.split(k_turn, flat.shape[0]), flat)
        proposed, log_jacobian = proposed.reshape(z.shape), log_jacobian.reshape(loglik.shape)
        new_loglik, new_logprior = loglik_all(proposed, observation), logprior_all(proposed, index)
        log_ratio = (new_logprior - logprior + tempering[:, None] * (new_loglik - loglik) + log_jacobian)
        accept = jnp.log(jax.random.uniform(k_accept, loglik.shape)) < jnp.nan_to_num(log_ratio, nan=-jnp.inf)
        z = jnp.where(accept[..., None], proposed, z)
        loglik, logprior = jnp.where(accept, new_loglik, loglik), jnp.where(accept, new_logprior, logprior)
        return (z, loglik, logprior), accept.mean(axis=1)

    @jax.jit
    def material(key, state, index, tempering, observation):
        """The material Metropolis-within-Gibbs update at each row's temperature (one render of
        the material bases per particle; the result is scored from them), after the rendered
        symmetry move where ``symmetry`` is "rendered"; returns (state, each row's material
        acceptance (R,), its turn acceptance (R,), NaN without the rendered turn, and the material
        kind's jump acceptance (R,), NaN without ``jump``)."""
        turned = jnp.full(state[1].shape[:1], jnp.nan)
        if symmetry == "rendered":
            key, k_turn = jax.random.split(key)
            state, turned = turn(k_turn, state, index, tempering, observation)
        z, loglik, logprior = state
        h = jnp.repeat(index, z.shape[1])
        lam = jnp.repeat(tempering, z.shape[1])

        def one(key, position, logprior_value, loglik_value, row_hypothesis, lam_value, rendered):
            state = RWState(position, logprior_value + lam_value * loglik_value)
            new, accepted, new_loglik, jumped = core.scored_material_move(
                key, state, observation, lam_value, lambda p: log_prior(p, row_hypothesis), jump, rendered,
                loglik_value)
            return new.position, new_loglik, accepted, jumped

        keys = jax.random.split(key, h.shape[0])
        flat = z.reshape(-1, z.shape[-1])
        # every particle's bases in one batched render, then the moves' arithmetic in chunks (chunks.py)
        rendered = jax.vmap(lambda k, p: core.material_renders(k, p, observation, jump))(keys, flat)
        moved, new_loglik, accepted, jumped = map_in_chunks(
            one, (keys, flat, logprior.reshape(-1), loglik.reshape(-1), h, lam, rendered),
            rendered[0].shape[-4] * rendered[0].shape[-3] * rendered[0].shape[-2])   # pixels x 4 bases
        moved = moved.reshape(z.shape)
        jumped = jumped.reshape(loglik.shape).mean(axis=1) if jump else jnp.full(loglik.shape[:1], jnp.nan)
        return (moved, new_loglik.reshape(loglik.shape), logprior_all(moved, index)), \
            accepted.reshape(loglik.shape).mean(axis=1), turned, jumped

    prior_gradient = jax.vmap(jax.vmap(jax.grad(log_prior)))

    def drift(z, loglik, index, tempering, directions, step, observation):
        """(R, N, k) the tempered log density's derivative along each of the k directions (R, d, k):
        the log prior's exactly, the log likelihood's as a forward difference of step GRADIENT_STEP
        (k renders per particle). A deterministic function of z, so the MH ratio below stays exact."""
        rows, n, d = z.shape
        k = directions.shape[-1]
        shifted = z[:, :, None, :] + GRADIENT_STEP * jnp.swapaxes(directions, 1, 2)[:, None]   # (R, N, k, d)
        ll = loglik_all(shifted.reshape(rows, n * k, d), observation).reshape(rows, n, k)
        h = jnp.broadcast_to(index[:, None], (rows, n))
        prior = jnp.einsum("rnd,rdk->rnk", prior_gradient(z, h), directions)
        g = jnp.nan_to_num(prior + tempering[:, None, None] * (ll - loglik[..., None]) / GRADIENT_STEP,
                           nan=0.0, posinf=0.0, neginf=0.0)
        # truncated drift (MALTA, Roberts and Tweedie 1996): a drift of at most DRIFT_LIMIT steps, so a
        # likelihood's cliff cannot throw a particle out of the world; still a function of z alone
        limit = DRIFT_LIMIT * 2.0 / step[:, None, None]
        norm = jnp.sqrt(jnp.sum(g ** 2, axis=-1, keepdims=True))
        return g * jnp.minimum(1.0, limit / jnp.maximum(norm, 1e-30))

    @jax.jit
    def gradient(key, state, index, tempering, directions, step, observation):
        """One preconditioned MALA sweep over the pose (Roberts and Tweedie 1996) at each row's
        temperature: in the coordinates u with z = z0 + directions u (directions: the Cholesky factor
        of the particles' pose covariance), u' = u + step^2 / 2 g(u) + step xi, accepted with the
        Hastings ratio of the forward and the reverse proposal. Returns (state, acceptance (R,))."""
        k_noise, k_accept = jax.random.split(key)
        z, loglik, logprior = state
        eps = step[:, None, None]
        g = drift(z, loglik, index, tempering, directions, step, observation)
        xi = jax.random.normal(k_noise, g.shape)
        du = 0.5 * eps ** 2 * g + eps * xi
        proposed = z + jnp.einsum("rdk,rnk->rnd", directions, du)
        finite = jnp.all(jnp.isfinite(proposed), axis=-1)
        proposed = jnp.where(finite[..., None], proposed, z)           # never rendered, never accepted
        new_loglik, new_logprior = loglik_all(proposed, observation), logprior_all(proposed, index)
        g_new = drift(proposed, new_loglik, index, tempering, directions, step, observation)
        forward = -0.5 * jnp.sum(xi ** 2, axis=-1)
        reverse = -0.5 * jnp.sum((-du - 0.5 * eps ** 2 * g_new) ** 2, axis=-1) / step[:, None] ** 2
        log_ratio = (new_logprior + tempering[:, None] * new_loglik - logprior - tempering[:, None] * loglik
                     + reverse - forward)
        uniform = jnp.log(jax.random.uniform(k_accept, loglik.shape))
        accept = finite & (uniform < jnp.nan_to_num(log_ratio, nan=-jnp.inf))
        z = jnp.where(accept[..., None], proposed, z)
        loglik, logprior = jnp.where(accept, new_loglik, loglik), jnp.where(accept, new_logprior, logprior)
        return (z, loglik, logprior), accept.mean(axis=1)

    @functools.partial(jax.jit, static_argnames=("material_every",))
    def sweeps(key, state, index, tempering, tril, centres, observation, total, material_every: int):
        """``total`` sweeps in one call: each a walk, and after every ``material_every``-th walk and the
        last one a material update, with the keys split as a loop over :func:`walk` and :func:`material`
        would split them (so a sweep-by-sweep loop gives the same draws). One compiled call per move, not
        one per sweep (on a GPU, dispatching the sweeps from the host is a large share of a posterior's
        time); ``total`` is traced, so the last move's longer run
        shares the compilation. Returns (the key left after the sweeps, state, and per row (R,) the mean
        acceptance of the walks, of the material updates, of their turns and of their jumps (NaN where
        the updates make no turn or no jump)."""
        zero = jnp.zeros(index.shape, jnp.float32)

        def one(i, carry):
            key, state, walked, updated, turned, jumped, count = carry
            key, k_walk, k_material = jax.random.split(key, 3)
            state, walk_rate = walk(k_walk, state, index, tempering, tril, centres, observation)
            made = ((i + 1) % material_every == 0) | (i == total - 1)
            state, rate, turn_rate, jump_rate = jax.lax.cond(
                made, lambda s: material(k_material, s, index, tempering, observation),
                lambda s: (s, zero, zero, zero), state)
            return (key, state, walked + walk_rate, updated + rate, turned + turn_rate, jumped + jump_rate,
                    count + made.astype(jnp.float32))

        key, state, walked, updated, turned, jumped, count = jax.lax.fori_loop(
            0, total, one, (key, state, zero, zero, zero, zero, jnp.float32(0.0)))
        return key, state, walked / total, updated / count, turned / count, jumped / count

    return Kernels(score, walk, material, parts, jax.jit(logprior_all), gradient, jax.jit(turn), chart, sweeps)


def kernels(core, kinds: bool, ridge: int, symmetry: str | None = None, chart: bool | None = None,
            jump: bool | None = None) -> Kernels:
    """The jitted moves of one core (cached: a core serves every image of a data set); ``symmetry``,
    ``chart`` (the walk in each particle's symmetry chart) and ``jump`` (the material kind's jump)
    default to the SMC's (:class:`~mitsuba_p3.infer.smc.SMCConfig`)."""
    from .smc import SMCConfig

    symmetry = SMCConfig.symmetry if symmetry is None else symmetry
    chart = SMCConfig.chart if chart is None else bool(chart)
    jump = SMCConfig.jump if jump is None else bool(jump)
    if symmetry not in SYMMETRY_MOVES:
        from ..errors import ConfigError

        raise ConfigError(f"symmetry must be one of {SYMMETRY_MOVES}, not {symmetry!r}")
    return _kernels(core, tuple(WALK_MASK.tolist()), kinds, ridge, symmetry, chart, jump)


def kernels_for(core, config) -> Kernels:
    """The kernels an SMC run under ``config`` (:class:`~mitsuba_p3.infer.smc.SMCConfig`) moves with."""
    return kernels(core, config.kinds, config.ridge, config.symmetry, config.chart, config.jump)


def mover(kernels: Kernels, index, observation, sweeps: int, material_every: int,
          tempering: np.ndarray | None = None, final_sweeps: int = 0, path: bool = False,
          gradient_sweeps: int = 0, final_gradient_sweeps: int = 0) -> Callable:
    """A move for :func:`mitsuba_p3.infer.tempering.step`: ``sweeps`` sweeps of every row at its
    temperature (or at ``tempering``), ``final_sweeps`` more once every row has reached lambda = 1,
    returning the moved state and the mean acceptance per row of the walks and of the material
    updates. ``gradient_sweeps`` (``final_gradient_sweeps`` once every row is at lambda = 1) MALA
    sweeps over the pose follow the walks (acceptance ``gradient``). With ``path`` the moved state
    keeps every sweep's particles, the start's included (M particles in, (sweeps + 1) M out):
    waste-free SMC's move (Dau and Chopin 2022)."""
    import jax
    import jax.numpy as jnp

    def move(key, state: TemperedState):
        lam = jnp.asarray(state.tempering if tempering is None else tempering, jnp.float32)
        # the walk's chart and covariance: each row's particles folded onto one symmetric copy (symmetry.py)
        position = np.asarray(state.position)
        centres = chart_centres(position)
        tril = jnp.asarray(walk_factors(folded(position, centres) if kernels.chart else position, state.scale))
        centres = jnp.asarray(centres, jnp.float32)
        particles = tuple(jnp.asarray(a) for a in state[:3])
        final = bool(np.all(state.tempering >= 1.0))      # every row at lambda = 1: the last move
        total = sweeps + (final_sweeps if final else 0)
        if path:                                           # waste-free keeps every sweep's states
            kept, walks, materials, turns, jumps = [particles], [], [], [], []
            for i in range(total):
                key, k_walk, k_material = jax.random.split(key, 3)
                particles, accepted = kernels.walk(k_walk, particles, index, lam, tril, centres, observation)
                walks.append(accepted)
                if (i + 1) % material_every == 0 or i == total - 1:
                    particles, accepted, turned, jumped = kernels.material(k_material, particles, index, lam,
                                                                           observation)
                    materials.append(accepted)
                    turns.append(turned)
                    jumps.append(jumped)
                kept.append(particles)
            rates = [np.mean(np.asarray(a), axis=0) for a in (walks, materials, turns, jumps)]
        else:
            key, particles, *rates = kernels.sweeps(key, particles, index, lam, tril, centres, observation,
                                                    jnp.int32(total), material_every=material_every)
        rates = dict(zip(("walk", "material", "turn", "jump"), (np.asarray(r) for r in rates)))
        gradients = []
        mala = gradient_sweeps + (final_gradient_sweeps if final else 0)
        if mala:
            # the step starts from the walk's adapted scale (how wide the target is against the particles'
            # spread) times the gradient move's own, and adapts between sweeps by the population's acceptance
            scale = np.asarray(state.scale) * state.gradient_scale
            directions = jnp.asarray(pose_directions(np.asarray(particles[0])))
            for _ in range(mala):
                key, k_gradient = jax.random.split(key)
                particles, accepted = kernels.gradient(k_gradient, particles, index, lam, directions,
                                                       jnp.asarray(gradient_step(scale)), observation)
                gradients.append(accepted)
                scale = scale * adaptation(np.asarray(accepted), TARGET_GRADIENT_ACCEPTANCE)
                if path:
                    kept.append(particles)
        if path:
            particles = tuple(jnp.concatenate([p[i] for p in kept], axis=1) for i in range(3))
        moved = state._replace(position=np.array(particles[0]), loglikelihood=np.array(particles[1]),
                               logprior=np.array(particles[2]))
        for name in ("turn", "jump"):                     # NaN: this move makes no turns, or no jumps
            if np.isnan(rates[name]).all():
                del rates[name]
        if gradients:
            rates["gradient"] = np.mean(np.asarray(gradients), axis=0)
        return moved, rates

    return move
