"""The primitives' four-fold symmetry, and the chart a random walk moves in.

Every primitive (box, ellipsoid, elliptic cylinder) is the same shape after a quarter turn about
the vertical axis that also swaps its x and y half-extents, and after a half turn. A posterior over
one object's pose therefore has four equivalent copies, a quarter turn apart, and the SMC's
symmetry move (:meth:`~mitsuba_p3.infer.model.PosteriorCore.symmetry_turn`) keeps its particles
spread over all four, as they should be.

That spread must not reach the random walk's proposal. The walk's covariance is its particles'
own (:func:`~mitsuba_p3.infer.move_scales.walk_factors`); over particles in four copies it is
dominated by the distance between copies (a yaw spread of a radian or more, x and y half-extents
mixed by the swap), not by the width of any one copy (about a milliradian and a millimetre where
the likelihood is sharp). Scaled to 25% acceptance, such a walk takes steps a thousandth of what
each copy allows in every other direction, and a particle cloud that has settled in a local
optimum of the joint pose (yaw x anisotropic size) stays there.

So the walk moves in a **chart**: each row's copies are folded onto one, centred on the row's
quarter-turn circular mean yaw mu (:func:`chart_centres`). A particle in copy q (its yaw
``round((theta - mu) / 90 deg)`` quarter turns from mu; :func:`quarters`) is turned back by q
(:func:`quarter_turn`), walked there with the covariance of the folded particles
(:func:`folded`), and turned forward by q again. The move is exact: in the chart's coordinates
u = T_q^-1(z) the walk is symmetric, so it is accepted with the target's ratio times the turn's
Jacobian |dz/du| at both ends; a step that lands in another copy q' (its yaw more than 45 degrees
from mu in the chart) is accepted with the full Hastings ratio, the reverse step's density taken in
q' 's chart (:func:`~mitsuba_p3.infer.smc_moves.kernels`' walk). The chart's centre is the
population's, fixed while the move runs, as the covariance is.

:func:`quarter_turn` takes the array module ``xp`` (``numpy`` or ``jax.numpy``), so the host's
folding for the covariance and the jitted walk share one formula.
"""
from __future__ import annotations

import numpy as np

from ..space import SLICES

THETA = SLICES["theta"].start
SCALE_X, SCALE_Y = SLICES["scale"].start, SLICES["scale"].start + 1
QUARTER = np.pi / 2


def yaw(z, xp=np):
    """The natural yaw theta in (-pi, pi) of positions z (..., 15): its logistic coordinate's."""
    return -np.pi + 2 * np.pi / (1 + xp.exp(-z[..., THETA]))


def quarter_turn(z, quarters, xp=np):
    """Positions z (..., 15) turned by ``quarters`` (..., integers) quarter turns, the x and y
    half-extents swapped for an odd number, and log |det dz'/dz| (...): the yaw's logistic coordinate
    is stretched by a turn (z = logit(u), u' = u + q / 4 (mod 1): dz'/dz = u (1 - u) / (u' (1 - u')));
    the swap's is 1 in absolute value. No turn (a multiple of four) leaves z exactly as it is."""
    quarters = xp.asarray(quarters)
    u0 = 1 / (1 + xp.exp(-z[..., THETA]))
    theta = -np.pi + 2 * np.pi * u0
    turned = xp.mod(theta + quarters * QUARTER + np.pi, 2 * np.pi) - np.pi
    u = xp.clip((turned + np.pi) / (2 * np.pi), 1e-7, 1 - 1e-7)
    still = quarters % 4 == 0
    theta_z = xp.where(still, z[..., THETA], xp.log(u) - xp.log1p(-u))
    odd = quarters % 2 == 1
    x = xp.where(odd, z[..., SCALE_Y], z[..., SCALE_X])
    y = xp.where(odd, z[..., SCALE_X], z[..., SCALE_Y])
    parts = [z[..., :THETA], theta_z[..., None], z[..., THETA + 1:SCALE_X], x[..., None], y[..., None],
             z[..., SCALE_Y + 1:]]
    log_jacobian = xp.where(still, 0.0, xp.log(u0) + xp.log1p(-u0) - xp.log(u) - xp.log1p(-u))
    return xp.concatenate(parts, axis=-1), log_jacobian


def quarters(z, centres, xp=np):
    """(R, N) integers: how many quarter turns each particle of z (R, N, 15) lies from its row's chart
    centre (R,), in (-2, 2]."""
    return xp.round((yaw(z, xp) - centres[:, None]) / QUARTER).astype(xp.int32)


def chart_centres(position, xp=np):
    """(R,) each row's chart centre: the circular mean of its particles' yaw taken modulo a quarter
    turn (the mean of exp(4 i theta), its angle / 4), so particles in any copy of one pose agree on it.
    Under numpy in float64; under ``jax.numpy`` in the positions' own precision."""
    theta = yaw(np.asarray(position, np.float64) if xp is np else position, xp)
    return xp.arctan2(xp.sin(4 * theta).mean(axis=-1), xp.cos(4 * theta).mean(axis=-1)) / 4


def folded(position, centres, xp=np):
    """Positions (R, N, 15) turned into their row's chart (the copy whose yaw is within 45 degrees of
    its centre): the population whose covariance the walk takes."""
    position = np.asarray(position, np.float64) if xp is np else position
    return quarter_turn(position, -quarters(position, centres, xp), xp)[0]
