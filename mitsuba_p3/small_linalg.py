"""Cholesky factors and solves of small symmetric positive definite matrices, with no LAPACK call.

The samplers factor many tiny matrices at once (the shading fields' K x K systems, K = 3 to
18, per particle and region; the colour's 3 x 3 precision per prior component) and solve with
the walk's 15 x 15 scale factor per run. Through
``jnp.linalg`` each batch becomes a LAPACK custom call, and the jaxlib releases of April to
July 2026 split such a batch over XLA's intra-op thread pool and wait for the pieces inside
a pool thread (jax-ml/jax#36927, fixed by running it serially). Two independent calls then
take both threads of a 2-core machine, each waiting for pieces that no thread is left to
run: the process hangs with every thread idle (seen under ``--noise fields``: a solve and
a log-determinant side by side). Made of elementwise products and sums, the factorisation
has no custom call and cannot wait on the pool.

Each function is a loop over the n columns (or rows) whose body works on whole rows at once,
picking row j with a one-hot mask rather than an index: under JAX the loop is a
``lax.fori_loop``, so a jitted caller gets one small loop body whatever n is, not n^3 / 6
straight-line multiply-adds (those made the samplers' fused sweeps minutes of compilation);
under numpy it is a Python loop over the same body. Each column costs n^2 rather than n j
operations, about twice the scalar count, which is nothing beside the renders at these sizes.

Every function takes matrices (..., n, n) and batches (and broadcasts) over the leading axes;
``xp`` is numpy or jax.numpy; a factor is the lower-triangular array L (..., n, n) with
A = L L'.
"""
from __future__ import annotations

import numpy as np


def _loop(n: int, body, init, xp, reverse: bool = False):
    """``init`` carried through ``body(i, carry)`` for i = 0 .. n-1 (or n-1 .. 0): a ``lax.fori_loop``
    under JAX, a Python loop under numpy."""
    if xp is np:
        carry = init
        for i in (reversed(range(n)) if reverse else range(n)):
            carry = body(i, carry)
        return carry
    from jax import lax

    if reverse:
        return lax.fori_loop(0, n, lambda k, carry: body(n - 1 - k, carry), init)
    return lax.fori_loop(0, n, body, init)


def _unit(i, n: int, dtype, xp):
    """The one-hot vector e_i (n,) (``i`` may be traced)."""
    return (xp.arange(n) == i).astype(dtype)


def cholesky(a, xp=np):
    """The lower Cholesky factor L (..., n, n) of SPD ``a`` (..., n, n), column by column."""
    n = a.shape[-1]

    def column(j, lower):
        e = _unit(j, n, a.dtype, xp)
        row = xp.sum(lower * e[:, None], axis=-2)                     # L[j, :], zero from column j on
        # v = a[:, j] - L L[j, :]': the column before scaling; its j-th entry is L[j, j]^2
        v = xp.sum(a * e, axis=-1) - xp.sum(lower * row[..., None, :], axis=-1)
        pivot = xp.sqrt(xp.sum(v * e, axis=-1))[..., None]
        below = (xp.arange(n) > j).astype(a.dtype)
        return lower + (below * v / pivot + e * pivot)[..., :, None] * e

    return _loop(n, column, xp.zeros_like(a), xp)


def forward(lower, b, xp=np):
    """L^-1 b for a lower-triangular ``lower`` (..., n, n) and right-hand sides b (..., n) (the batch
    axes broadcast: one factor may serve several right-hand sides)."""
    n = lower.shape[-1]

    def row(i, y):
        e = _unit(i, n, b.dtype, xp)
        l_i = xp.sum(lower * e[:, None], axis=-2)                     # L[i, :]
        value = (xp.sum(b * e, axis=-1) - xp.sum(l_i * y, axis=-1)) / xp.sum(l_i * e, axis=-1)
        return y + value[..., None] * e

    shape = np.broadcast_shapes(lower.shape[:-1], b.shape)
    return _loop(n, row, xp.zeros(shape, b.dtype), xp)


def backward(lower, y, xp=np):
    """L^-T y for a lower-triangular ``lower`` (..., n, n) and right-hand sides y (..., n)."""
    n = lower.shape[-1]

    def row(i, x):
        e = _unit(i, n, y.dtype, xp)
        l_i = xp.sum(lower * e, axis=-1)                              # L[:, i], the i-th row of L'
        value = (xp.sum(y * e, axis=-1) - xp.sum(l_i * x, axis=-1)) / xp.sum(l_i * e, axis=-1)
        return x + value[..., None] * e

    shape = np.broadcast_shapes(lower.shape[:-1], y.shape)
    return _loop(n, row, xp.zeros(shape, y.dtype), xp, reverse=True)


def solve(lower, b, xp=np):
    """A^-1 b for A = L L' (:func:`cholesky`) and right-hand sides b (..., n)."""
    return backward(lower, forward(lower, b, xp), xp)


def log_det(lower, xp=np):
    """log det A (...) for A = L L'."""
    return 2 * xp.sum(xp.log(xp.diagonal(lower, axis1=-2, axis2=-1)), axis=-1)
