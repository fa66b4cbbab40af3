"""What independent SMC runs say together: each hypothesis's pooled evidence, whether the answer
is decided, and how far the runs disagree.

Every run (row) of hypothesis h gives an unbiased estimate of its evidence Z_h, so the runs pool
as the log of their mean (:func:`pooled_evidence`). Their spread is the Monte Carlo error that the
decision between hypotheses must beat (:func:`decision`), and the spread of the leading
hypothesis's runs, the **island gap**, is the SMC's convergence diagnostic: two runs that found
the same posterior agree to their estimates' error (about a nat with each run's importance-sampling
estimate, :mod:`~mitsuba_p3.infer.importance`); a run that missed the pose estimates tens of nats low
(:func:`island_gap`). Against the empty floor, the evidence says whether the image shows
an object at all (:func:`object_evidence`), and a run whose particles never rendered the object is
counted as lost (:func:`mark_lost_runs`).
"""
from __future__ import annotations

import functools
from typing import TYPE_CHECKING, Callable

import numpy as np

from ..shapes import SHAPES
from ..space import SLICES

if TYPE_CHECKING:
    from .hypotheses import Hypotheses
    from .smc import Rows


def _per_hypothesis(rows, hypotheses: int, reduce: Callable[[np.ndarray], float]) -> np.ndarray:
    """``reduce`` of each hypothesis's rows' log evidence estimates (-inf: no row)."""
    return np.array([reduce(mine) if len(mine := rows.log_evidence[rows.index == h]) else -np.inf
                     for h in range(hypotheses)])


def pooled_evidence(rows, hypotheses: int) -> np.ndarray:
    """log Z_h per hypothesis: the log of the mean of its rows' unbiased estimates (-inf: no row)."""
    return _per_hypothesis(rows, hypotheses, lambda mine: np.logaddexp.reduce(mine) - np.log(len(mine)))


def island_range(rows, hypotheses: int) -> tuple[np.ndarray, np.ndarray]:
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


def shape_weights(statistics: dict) -> dict:
    """p(shape | I) from a run's statistics: each shape's hypotheses' weights summed (with material
    kinds as hypotheses, ``sphere/shiny`` and ``sphere/matte`` are both the sphere's)."""
    weights = {shape: 0.0 for shape in SHAPES}
    for name, hypothesis in statistics["hypotheses"].items():
        weights[name.split("/")[0]] += hypothesis["weight"]
    return weights


def island_gap(statistics: dict) -> float | None:
    """The spread (max - min, nats) of the leading hypothesis's runs' log evidence: how far two
    independent SMC runs of the answer disagree. About a nat when they explored alike; tens of nats when
    one run missed the pose the other found. None with a single run."""
    hypotheses = statistics["hypotheses"]
    leader = max(hypotheses, key=lambda name: hypotheses[name]["weight"])
    runs = hypotheses[leader].get("island_log_evidence") or []
    return float(max(runs) - min(runs)) if len(runs) > 1 else None


# a half-extent this small (metres) is far below a pixel: the render is the empty floor
EMPTY_SCALE = 1e-5


@functools.lru_cache(maxsize=4)
def _log_likelihood(core) -> Callable:
    """One particle's image score (the window's term left out: the empty floor has no object to place),
    jitted once per core (run eagerly, op by op, the JAX tracer's
    render took 0.9 of a GPU posterior's 1.3 s)."""
    import jax

    return jax.jit(core.image_log_likelihood)


def object_evidence(core, observation, rows: Rows, space: Hypotheses, pooled: np.ndarray) -> dict:
    """Whether the image shows an object the model explains: the log evidence of "one object" (the
    hypotheses' evidence under their prior) against the empty floor, a model without parameters whose
    evidence is its likelihood, scored on the same window by the same likelihood. A negative log
    Bayes factor says the floor alone explains the image better than any object would."""
    import jax.numpy as jnp

    z = np.array(rows.state.position[0, 0], np.float32)
    z[SLICES["scale"]] = np.log(EMPTY_SCALE)
    empty = float(_log_likelihood(core)(jnp.asarray(z), observation))
    one_object = float(np.logaddexp.reduce(space.log_prior + pooled))
    return {"empty_log_likelihood": empty, "log_bayes_factor_object": one_object - empty}


# a run whose best final particle got less than this share of the way from the empty floor's log likelihood
# to the best any run reached never rendered the object (a wrong shape at the right pose gets most of the way,
# a lost run hardly any)
LOST_SHARE = 0.1


def mark_lost_runs(statistics: dict, rows: Rows, space: Hypotheses) -> None:
    """Count, per hypothesis, the runs that lost the object: their best final particle explains the window
    hardly better than the empty floor, against what the best run reached (:data:`LOST_SHARE`). Such a
    run's particles all render (nearly) the same image, their likelihoods are equal, and the tempering
    rule, which reads equal likelihoods as a posterior already found, takes it straight to lambda = 1:
    its evidence is about the floor's, whatever the hypothesis, and the island gap cannot show it when
    both runs of a hypothesis lost the object alike."""
    empty = statistics.get("empty_log_likelihood")
    if empty is None:
        return
    best = rows.state.loglikelihood.max(axis=1)
    reach = float(best.max()) - empty
    for h, name in enumerate(space.names):
        mine = rows.index == h
        lost = (best[mine] - empty < LOST_SHARE * reach) if reach > 0 else np.zeros(int(mine.sum()), bool)
        statistics["hypotheses"][name]["lost_runs"] = int(np.sum(lost))
