"""Cholesky factors and solves of small symmetric positive definite matrices, written out.

The samplers factor many tiny matrices at once (the shading fields' K x K systems, K = 3 to
18, per particle and region; the colour's 3 x 3 precision per prior component) and solve with
the walk's 15 x 15 scale factor per run. Through
``jnp.linalg`` each batch becomes a LAPACK custom call, and the jaxlib releases of April to
July 2026 split such a batch over XLA's intra-op thread pool and wait for the pieces inside
a pool thread (jax-ml/jax#36927, fixed by running it serially). Two independent calls then
take both threads of a 2-core machine, each waiting for pieces that no thread is left to
run: the process hangs with every thread idle (seen under ``--noise fields``: a solve and
a log-determinant side by side). Written out with elementwise operations the factorisation
has no custom call, cannot wait on the pool, and for these sizes costs no more.

Every function takes matrices (..., n, n) and batches over the leading axes; ``xp`` is numpy
or jax.numpy. The loops run at trace time (n is static), so a jitted caller gets straight-line
code of n^3 / 6 multiply-adds.
"""
from __future__ import annotations

import numpy as np


def cholesky(a, xp=np) -> list:
    """The lower Cholesky factor of SPD ``a`` (..., n, n) as rows of columns: ``L[i][j]`` (...) for
    j <= i (:func:`as_matrix` stacks it)."""
    n = a.shape[-1]
    factor = [[None] * n for _ in range(n)]
    for j in range(n):
        diagonal = a[..., j, j] - sum((factor[j][k] ** 2 for k in range(j)), xp.zeros_like(a[..., j, j]))
        factor[j][j] = xp.sqrt(diagonal)
        for i in range(j + 1, n):
            off = a[..., i, j] - sum((factor[i][k] * factor[j][k] for k in range(j)), xp.zeros_like(a[..., i, j]))
            factor[i][j] = off / factor[j][j]
    return factor


def rows(lower) -> list:
    """A lower-triangular matrix (..., n, n) as a factor of :func:`cholesky`'s form, so that
    :func:`forward` and :func:`backward` solve with a factor made elsewhere (the walk's scale)."""
    n = lower.shape[-1]
    return [[lower[..., i, j] if j <= i else None for j in range(n)] for i in range(n)]


def as_matrix(factor: list, xp=np):
    """(..., n, n) the factor of :func:`cholesky` as a lower-triangular array."""
    n = len(factor)
    zero = xp.zeros_like(factor[0][0])
    return xp.stack([xp.stack([factor[i][j] if j <= i else zero for j in range(n)], axis=-1) for i in range(n)],
                    axis=-2)


def forward(factor: list, b, xp=np):
    """L^-1 b for right-hand sides b (..., n)."""
    n = len(factor)
    y = []
    for i in range(n):
        y.append((b[..., i] - sum((factor[i][k] * y[k] for k in range(i)), xp.zeros_like(b[..., i]))) / factor[i][i])
    return xp.stack(y, axis=-1)


def backward(factor: list, y, xp=np):
    """L^-T y for right-hand sides y (..., n)."""
    n = len(factor)
    x = [None] * n
    for i in reversed(range(n)):
        x[i] = (y[..., i] - sum((factor[k][i] * x[k] for k in range(i + 1, n)), xp.zeros_like(y[..., i]))
                ) / factor[i][i]
    return xp.stack(x, axis=-1)


def solve(factor: list, b, xp=np):
    """A^-1 b for A = L L' (:func:`cholesky`) and right-hand sides b (..., n)."""
    return backward(factor, forward(factor, b, xp), xp)


def log_det(factor: list, xp=np):
    """log det A (...) for A = L L'."""
    return 2 * sum(xp.log(factor[i][i]) for i in range(len(factor)))
