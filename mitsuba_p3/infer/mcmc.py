"""Metropolis-Hastings over many chains at once (blackjax's rmh kernel, a jitted JAX loop).

Phases, all seeded:

1. **Initialisation.** Draw ``init_candidates`` positions from the prior, score
   them in batches, and start the chains at the best ones, stratified over the
   modes (below) so that every plausible mode starts with some chains.
2. **Tuning.** ``tune_rounds`` rounds of ``tune_steps``. After each round the
   walk becomes a full-covariance Gaussian (adaptive Metropolis, Haario et al.
   2001): the within-mode covariance of the later half of the rounds so far,
   pooled over chains and modes, times 2.38^2/d, times a factor corrected towards
   an acceptance rate of 0.25 (inside the 20-50% band; see
   :func:`_acceptance_correction`). The paper's single scalar sigma mixes poorly:
   colour, k_a and k_d are strongly correlated, and the dimensions differ in scale.
   Chains whose mean log density trails the best chain's by more than
   ``cull_margin`` nats are restarted from a good chain (tuning only).
3. **Burn-in**, then **sampling** with the proposal fixed, so the kept draws
   come from one valid MH kernel.

The sampler knows nothing of scenes: a :class:`Target` hands it the log density,
a way to draw starting points, and a ``mode_fn`` that labels each position with
one of ``modes`` discrete modes (for image posteriors, a shape class times a
material kind: :meth:`mitsuba_p3.fit.priors.Prior.hypothesis`). The posterior
has separated modes along these labels. Each step of a chain is one of:

- a **walk** (probability 1 - ``mode_jump_probability``): a Gaussian step with
  the walk covariance;
- a **mode jump** (Tjelmeland and Hegstad 2001): to another mode m' chosen
  uniformly, by adding mu_m' - mu_m, the difference of the modes' mean positions
  learnt in tuning; void unless it lands in m' (so the reverse jump is always
  available and the proposal is symmetric). A matte cube at its best size and
  colour is proposed as a shiny cylinder at that mode's best values. A void
  proposal is a null move.

(Per-mode walk covariances, with affine jumps and their Jacobian, were tried: on
a known three-mode target their chains settled in whichever modes tuning had
visited, so the pooled covariance stays.)

After every walk the target's ``walk_move`` (if any) runs: for image posteriors
the symmetry move of :meth:`mitsuba_p3.infer.model.PosteriorCore.symmetry_move`,
which costs no render. After the ``walks_per_step`` walks of a recorded step the
target's ``step_move`` (if any) runs: for image posteriors the material
Metropolis-within-Gibbs update (:meth:`~mitsuba_p3.infer.model.PosteriorCore.material_move`);
``walk_mask`` then keeps the walk off the dimensions that move updates.

The pieces are pure functions over NamedTuple states, as in blackjax:
:func:`init` makes the chains' state, :func:`build_step` one recorded step of every
chain, :func:`sample` the phases around them.
"""
from __future__ import annotations

import functools
from dataclasses import asdict, dataclass
from typing import Callable, NamedTuple

import numpy as np

from .tuning import Proposal, acceptance_correction, learn_proposal, move_statistics



@dataclass(frozen=True)
class SamplerConfig:
    chains: int = 10
    steps: int = 600             # kept draws per chain
    burn_in: int = 50
    tune_rounds: int = 4
    tune_steps: int = 50
    initial_scale: float = 0.05
    target_acceptance: float = 0.25  # of the walk; the tuning corrects rates outside 0.2-0.3
    mode_jump_probability: float = 0.2
    symmetry_moves: bool = True
    material_gibbs: bool = True  # Metropolis-within-Gibbs material updates (one basis render per step)
    walks_per_step: int = 3      # random-walk steps per recorded step (before the material update)
    init_candidates: int = 400
    cull_margin: float = 20.0    # nats
    block: int = 50              # steps per compiled call (progress granularity)
    seed: int = 0

    def __post_init__(self):
        from ..errors import ConfigError, check_counts, check_positive

        check_counts(self, {"chains": 2, "steps": 1, "burn_in": 0, "tune_rounds": 0, "tune_steps": 1,
                            "walks_per_step": 1, "init_candidates": 1, "block": 1, "seed": 0}, "sampler ")
        check_positive(self, ("initial_scale", "cull_margin"), "sampler ")
        for name in ("target_acceptance", "mode_jump_probability"):
            if not 0 <= getattr(self, name) < 1:
                raise ConfigError(f"sampler {name.replace('_', '-')} must lie in [0, 1); got {getattr(self, name)!r}")


class Target(NamedTuple):
    """What the sampler knows of a model: functions, all jax-traceable except ``initial_fn``.

    Hashable (a tuple of functions and numbers), so a compiled sampler is reused for
    the same target; ``observation`` is an argument of the compiled code, not part of it."""

    logdensity_fn: Callable          # (z, observation) -> log density
    initial_fn: Callable             # (rng, n) -> (n, d) candidate starting points (numpy)
    mode_fn: Callable                # z (..., d) -> int mode label in [0, modes)
    modes: int
    walk_move: Callable | None = None   # (key, state) -> state: leaves the target invariant, after every walk
    step_move: Callable | None = None   # (key, state, observation) -> (state, accepted): after a step's walks
    walk_mask: tuple | None = None      # per dimension 1 (walked) or 0 (left to step_move); None: all walked

class SamplerRun(NamedTuple):
    positions: np.ndarray         # (chains, draws, 15) unconstrained
    logdensity: np.ndarray        # (chains, draws)
    accepted: np.ndarray          # (chains, draws) bool
    proposal: dict                # the final proposal: per-mode means, Cholesky factors, known flags
    tuning: list                  # per round: acceptance rates, factor, restarts, modes known
    config: dict
    statistics: dict              # acceptance rates of the kept draws' walks and jumps


def _transition(proposal: Proposal, mode_fn: Callable, modes: int, jump_probability: float):
    """The symmetric proposal mixture of the module docstring, for blackjax's rmh kernel."""
    import jax
    import jax.numpy as jnp

    tril, means, known = proposal

    def generate(key, position):
        """A proposal for one chain, and whether it is a mode jump."""
        k_choice, k_noise, k_target = jax.random.split(key, 3)
        walk = position + tril @ jax.random.normal(k_noise, position.shape)
        # a mode jump shifts by the difference of the modes' means; void unless it lands in the target
        current = mode_fn(position)
        target = (current + jax.random.randint(k_target, (), 1, modes)) % modes
        shifted = position + means[target] - means[current]
        lands = (mode_fn(shifted) == target) & known[target] & known[current]
        is_jump = jax.random.uniform(k_choice) < jump_probability
        return jnp.where(is_jump, jnp.where(lands, shifted, position), walk), is_jump

    return generate


class _Compiled(NamedTuple):
    """The sampler settings the compiled block depends on (the rest change only the loop around it)."""
    chains: int
    block: int
    walks_per_step: int
    mode_jump_probability: float
    symmetry_moves: bool

    @classmethod
    def of(cls, config: SamplerConfig) -> "_Compiled":
        return cls(*(getattr(config, name) for name in cls._fields))


def init(positions, logdensities):
    """The chains' state (blackjax's ``RWState``) from starting positions (chains, d) and their log densities."""
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import RWState

    return RWState(jnp.asarray(positions), jnp.asarray(logdensities))


def build_step(target: Target, config: _Compiled):
    """One recorded step of every chain: ``step(key, states, proposal, observation) -> (states, info)``.

    A step is ``config.walks_per_step`` proposals of the mixture (walk or mode jump),
    each followed by the target's ``walk_move`` (when ``config.symmetry_moves``), then
    the target's ``step_move``. ``info`` is (positions, log densities, move counts);
    the move counts per chain are (walk accepted, walk proposed, jump accepted,
    jump proposed), a void proposal (no move) counting as neither."""
    import jax
    import jax.numpy as jnp
    from blackjax.mcmc.random_walk import build_rmh

    kernel = build_rmh()

    def step(key, states, proposal, observation):
        generate = _transition(Proposal(*proposal), target.mode_fn, target.modes, config.mode_jump_probability)
        logdensity = lambda z: target.logdensity_fn(z, observation)  # noqa: E731

        def walk(states, key):
            k_propose, k_walk, k_symmetry = jax.random.split(key, 3)
            proposed, jumps = jax.vmap(generate)(jax.random.split(k_propose, config.chains), states.position)
            keys = jax.random.split(k_walk, config.chains)
            new, info = jax.vmap(lambda k, s, p: kernel(k, s, logdensity, lambda _, __: p))(keys, states, proposed)
            real = jnp.any(proposed != states.position, axis=-1)
            is_walk, is_jump = real & ~jumps, real & jumps
            moves = jnp.stack([info.is_accepted & is_walk, is_walk, info.is_accepted & is_jump, is_jump], axis=-1)
            if config.symmetry_moves and target.walk_move is not None:
                new = jax.vmap(target.walk_move)(jax.random.split(k_symmetry, config.chains), new)
            return new, moves.astype(jnp.int32)

        k_walks, k_extra = jax.random.split(key)
        states, moves = jax.lax.scan(walk, states, jax.random.split(k_walks, config.walks_per_step))
        if target.step_move is not None:
            states, _ = jax.vmap(target.step_move, in_axes=(0, 0, None))(
                jax.random.split(k_extra, config.chains), states, observation)
        return states, (states.position, states.logdensity, moves.sum(axis=0))

    return step


@functools.lru_cache(maxsize=8)
def _block_runner(target: Target, config: _Compiled):
    """A jitted ``run(key, states, proposal, observation)`` running ``config.block`` steps of every
    chain. Cached: the same target (e.g. one :class:`PosteriorCore`'s bound methods) reuses the
    compiled function for every observation of the same shape."""
    import jax

    step = build_step(target, config)

    @jax.jit
    def run(key, states, proposal, observation):
        return jax.lax.scan(lambda s, k: step(k, s, proposal, observation), states,
                            jax.random.split(key, config.block))

    return run


def _cull(states, logdensity: np.ndarray, margin: float, rng: np.random.Generator):
    """Restart chains whose highest log density in a round trails the best chain's by > margin.

    The highest, not the mean: a chain still climbing into a good mode has already
    reached high densities, while one stuck in a poor local mode has not."""
    import jax.numpy as jnp

    peak = logdensity.max(axis=0)
    good = np.flatnonzero(peak >= peak.max() - margin)
    bad = np.flatnonzero(peak < peak.max() - margin)
    if len(bad) == 0:
        return states, 0
    source = np.arange(len(peak))
    source[bad] = rng.choice(good, size=len(bad))
    index = jnp.asarray(source)
    return type(states)(states.position[index], states.logdensity[index]), int(len(bad))


@functools.lru_cache(maxsize=8)
def _batch_logdensity(logdensity_fn: Callable):
    """The jitted, vmapped ``logdensity_fn(z, observation)`` over positions (cached like the runner)."""
    import jax

    return jax.jit(jax.vmap(logdensity_fn, in_axes=(0, None)))


def initial_positions(target: Target, config: SamplerConfig, rng: np.random.Generator, observation=()):
    """The best of ``init_candidates`` draws of ``target.initial_fn`` (batched evaluation),
    stratified by mode, and their log densities.

    Chains go round-robin to the modes in order of their best candidate, so every
    plausible mode starts with some chains; culling during tuning removes the
    hopeless ones."""
    candidates = np.asarray(target.initial_fn(rng, max(config.init_candidates, config.chains)), np.float32)
    scores = np.asarray(_batch_logdensity(target.logdensity_fn)(candidates, observation))
    scores = np.where(np.isfinite(scores), scores, -np.inf)
    order = np.argsort(-scores)
    labels = np.asarray(target.mode_fn(candidates[order]))
    queues = [list(order[labels == m]) for m in dict.fromkeys(labels.tolist())]  # modes by best candidate
    chosen = []
    while len(chosen) < config.chains:
        for queue in queues:
            if queue and len(chosen) < config.chains:
                chosen.append(queue.pop(0))
    chosen = np.array(chosen)
    return candidates[chosen], scores[chosen].astype(np.float32)


def sample(target: Target, config: SamplerConfig | None = None,
           progress: Callable[[str, int, int], None] | None = None, observation=()) -> SamplerRun:
    """Run initialisation, tuning, burn-in and sampling of ``target``; returns the kept draws.

    ``observation`` (a pytree) is the second argument of the target's functions: the
    data enter the compiled sampler as an argument, so a second image with the same
    target (e.g. a shared :class:`PosteriorCore`'s methods) runs without recompiling."""
    import jax
    import jax.numpy as jnp

    config = config or SamplerConfig()
    rng = np.random.default_rng(config.seed)
    key = jax.random.PRNGKey(config.seed)
    start, scores = initial_positions(target, config, rng, observation)
    states = init(start, scores)
    dimension = start.shape[1]
    mask = np.ones(dimension, np.float32) if target.walk_mask is None else np.asarray(target.walk_mask, np.float32)
    proposal = Proposal.isotropic(config.initial_scale, mask, target.modes)
    factor = 1.0
    run = _block_runner(target, _Compiled.of(config))
    tuning = []
    blocks_per_round = max(1, -(-config.tune_steps // config.block))
    total = (config.tune_rounds * blocks_per_round + -(-config.burn_in // config.block)
             + -(-config.steps // config.block)) * config.block
    done = 0

    def advance(states, phase, blocks):
        """Run ``blocks`` compiled blocks; the per-step draws, log densities and move statistics."""
        nonlocal key, done
        out = []
        for _ in range(blocks):
            key, sub = jax.random.split(key)
            states, draws = run(sub, states, tuple(jnp.asarray(a) for a in proposal), observation)
            out.append([np.asarray(a) for a in draws])
            done += config.block
            if progress:
                progress(phase, done, total)
        if not out:
            return states, None
        return states, [np.concatenate(parts) for parts in zip(*out)]

    history = []
    for round_index in range(config.tune_rounds):
        states, (positions, logdensities, moves) = advance(states, "tuning", blocks_per_round)
        statistics = move_statistics(moves)
        # no culling in the first round: its chains are still converging into their modes
        states, culled = _cull(states, logdensities, config.cull_margin, rng) if round_index else (states, 0)
        history.append(positions[len(positions) // 4:].reshape(-1, dimension))
        factor *= acceptance_correction(statistics["walk_acceptance"], config.target_acceptance)
        # the covariance window: the later half of the rounds so far (Stan-like growing windows)
        window = np.concatenate(history[len(history) // 2:])
        learnt = learn_proposal(window, np.asarray(target.mode_fn(window)), target.modes, mask, factor)
        # a mode found earlier stays a jump target (with its last mean) when no chain is in it now
        kept = proposal.known & ~learnt.known
        proposal = learnt._replace(means=np.where(kept[:, None], proposal.means, learnt.means),
                                   known=learnt.known | kept)
        tuning.append({"round": round_index, **statistics, "factor": factor, "restarted": culled,
                       "modes_known": proposal.known.tolist()})

    states, _ = advance(states, "burn-in", -(-config.burn_in // config.block))
    states, (positions, logdensity, moves) = advance(states, "sampling", -(-config.steps // config.block))
    # scan stacks (steps, chains, ...): move chains first and trim to the requested count
    positions = positions.swapaxes(0, 1)[:, :config.steps]
    logdensity = logdensity.swapaxes(0, 1)[:, :config.steps]
    moves = moves.swapaxes(0, 1)[:, :config.steps]
    return SamplerRun(positions, logdensity, (moves[..., 0] + moves[..., 2]) > 0, proposal._asdict(), tuning,
                      asdict(config), move_statistics(moves))
