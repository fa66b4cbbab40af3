"""Per-particle arithmetic over a batch of renders, in chunks that stay in the CPU's cache.

A sampler's step renders every particle in one batched callback (:mod:`~mitsuba_p3.infer.render_functions`)
and then scores each render: its residual, the shading fields' region masks and the inner products
of :mod:`mitsuba_p3.fit.fields`, a few values per pixel. Under ``vmap`` XLA computes each of those
per-pixel intermediates for the whole batch before the next (the masks times the monomials of 1,536
renders of 56 x 72 pixels alone are 220 MB), so on a CPU the arithmetic streams through main memory
and waits on it. ``lax.map`` with a ``batch_size`` runs the same vmapped program on one chunk after
another; a chunk of about :data:`CHUNK_PIXELS` pixels keeps its intermediates in the cache. The
values are the same program's (only the batch's length differs), so they agree with ``vmap``'s to
float32 rounding.

On a GPU the whole batch is one launch (:func:`~mitsuba_p3.render.jax_tracer.batching_for`, the rule
the JAX tracer's batches follow), and the chunks would only serialise it: there it stays ``vmap``.
The renders are never made in chunks: each chunk would pay a callback and Mitsuba's launch.
"""
from __future__ import annotations

from typing import Callable

# pixels per chunk: 16 renders of 56 x 72, 65 of 28 x 36 (a chunk that fits the cache)
CHUNK_PIXELS = 65536


def chunk_size(pixels: int) -> int:
    """How many renders of ``pixels`` pixels one chunk holds (at least one)."""
    return max(1, CHUNK_PIXELS // max(1, int(pixels)))


def map_in_chunks(fn: Callable, xs: tuple, pixels: int):
    """``jax.vmap(fn)(*xs)``, computed in chunks of :func:`chunk_size` (``pixels``) elements on a CPU
    (``lax.map``; the module docstring) and whole on a GPU. ``fn`` must not render: a callback inside
    it would run once per chunk."""
    import jax

    from ..render.jax_tracer import batching_for

    if batching_for() == "vmap":
        return jax.vmap(fn)(*xs)
    return jax.lax.map(lambda args: fn(*args), xs, batch_size=chunk_size(pixels))
