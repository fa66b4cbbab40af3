"""The renderers as JAX functions: params -> image, under ``jit`` and ``vmap``.

A sampler written in JAX needs the render inside its program. Two ways in:

- :func:`mitsuba_render_function`: Mitsuba renders through a callback. Under ``vmap`` over particles
  the callback receives every particle's parameters at once (``vmap_method="expand_dims"``), so one
  step of all particles is one batched Mitsuba launch. Where JAX has ``buffer_callback``, XLA hands
  the callback its output buffers and Dr.Jit renders into them (DLPack, no copy through the host);
  else ``jax.pure_callback`` returns numpy images that XLA copies in;
- :func:`jax_render_function`: the pure-JAX tracer, no callback: the whole likelihood stays one JAX
  program (on a GPU, on the device), with a custom ``vmap`` rule that hands a batch to the tracer's
  batched render.

Both can return the material bases instead of the image and can render a window of the image only.
"""
from __future__ import annotations

from typing import Callable

import numpy as np

from ..render.contract import OBJECT_SHAPES
from ..space import OBJECT_KEYS


def in_place_available() -> bool:
    """Whether this JAX can hand a callback its output buffers (``jax.experimental.buffer_callback``)."""
    try:
        from jax.experimental.buffer_callback import buffer_callback  # noqa: F401
    except ImportError:
        return False
    return True


def _wait_for_inputs(context) -> None:
    """On a GPU, XLA calls a buffer callback when it would launch it, not when its inputs are ready:
    wait for XLA's stream (the CUDA driver's ``cuStreamSynchronize``) before reading them. A no-op on
    the CPU, which has no stream."""
    import jax

    try:
        stream = context.stream
    except jax.errors.JaxRuntimeError:      # "GPU context is not available": the CPU
        return
    if stream:
        import ctypes

        ctypes.CDLL("libcuda.so.1").cuStreamSynchronize(ctypes.c_void_p(stream))


def mitsuba_render_function(renderer, bases: bool = False, window: tuple[int, int] | None = None,
                            objects: bool = False, in_place: bool | None = None) -> Callable:
    """A JAX function params -> image(s) that renders with Mitsuba.

    Works on one parameter set (image (H, W, 3)) and under ``jax.vmap`` (the
    callback then gets all sets at once and renders them in one launch). With
    ``bases`` it returns the material bases (H, W, 4, 3) of ``renderer.render_bases``.
    With ``window`` (height, width) the function is ``render(params, offset)``: only the
    window of the image whose top-left pixel is ``offset`` (2,) (:meth:`MitsubaRenderer.window`).
    With ``objects`` it returns (image or bases, the pixels the object covers (H, W) bool), both from
    the one render: the shading fields' regions without tracing the object again in JAX.

    ``in_place``: XLA hands the callback its output buffers and Dr.Jit renders straight into them
    (:meth:`MitsubaRenderer.render_into`, the buffers mapped through DLPack): no image is copied to
    the host and back, which on a GPU is most of a small render's cost. Otherwise
    ``jax.pure_callback``: the images come back as numpy arrays and XLA copies them in. Both give
    the same values. The default follows the device: in place where Mitsuba renders on a GPU (and
    this JAX has ``buffer_callback``); on the CPU the numpy copies cost no more than Dr.Jit's
    interleaving of the channels into XLA's buffer (``scripts/bench_render.py --callbacks``).
    """
    import jax
    import jax.numpy as jnp

    if in_place is None:
        in_place = bool(getattr(renderer, "on_device", False)) and in_place_available()
    height, width = window or (renderer.height, renderer.width)
    pixel = (4, 3) if bases else (3,)
    views = {}

    def prepared(arrays):
        """The renderer (or the window's view) and the flattened parameter batch of a callback's inputs."""
        if window:
            # the offset is the same for the whole batch (it belongs to the observation)
            top, left = (int(v) for v in np.asarray(arrays[-1]).reshape(-1, 2)[0])
            arrays = arrays[:-1]
            if (top, left) not in views:
                views.clear()
                views[top, left] = renderer.window(top, left, height, width)
            view = views[top, left]
        else:
            view = renderer
        # Under vmap an argument that is not batched arrives with size-1 leading axes:
        # broadcast every argument to the common batch shape, then flatten it.
        leading = [np.shape(a)[:np.ndim(a) - len(OBJECT_SHAPES[k])] for k, a in zip(OBJECT_KEYS, arrays)]
        batch_shape = np.broadcast_shapes(*leading)
        count = int(np.prod(batch_shape, dtype=np.int64))
        params = {key: np.broadcast_to(a, batch_shape + OBJECT_SHAPES[key]).reshape((count,) + OBJECT_SHAPES[key])
                  for key, a in zip(OBJECT_KEYS, arrays)}
        return view, params, batch_shape

    def host(*arrays):
        view, params, batch_shape = prepared(arrays)
        out = (view.render_bases if bases else view.render)(params, **({"objects": True} if objects else {}))
        images, covered = out if objects else (out, None)
        images = np.asarray(images, np.float32).reshape(batch_shape + (height, width) + pixel)
        return (images, np.asarray(covered, bool).reshape(batch_shape + (height, width))) if objects else images

    def host_into(context, out, *arrays):
        _wait_for_inputs(context)
        # the parameters are a few numbers per image: read on the host (a device buffer through Dr.Jit)
        view, params, _ = prepared([renderer.host_array(a) for a in arrays])
        images, covered = out if objects else (out, None)
        view.render_into(params, images, covered, bases=bases)

    def render(params: dict, offset=None):
        batch_shape = jnp.shape(params["theta"])
        image = jax.ShapeDtypeStruct(batch_shape + (height, width) + pixel, jnp.float32)
        extra = [jnp.asarray(offset, jnp.int32)] if window else []
        inputs = [params[k] for k in OBJECT_KEYS] + extra
        if not in_place:
            out = (image, jax.ShapeDtypeStruct(batch_shape + (height, width), jnp.bool_)) if objects else image
            return jax.pure_callback(host, out, *inputs, vmap_method="expand_dims")
        from jax.experimental.buffer_callback import buffer_callback

        # the object's pixels travel as float32 (a format every DLPack importer maps), read back as bool
        out = (image, jax.ShapeDtypeStruct(batch_shape + (height, width), jnp.float32)) if objects else image
        result = buffer_callback(host_into, out, vmap_method="expand_dims")(*inputs)
        return (result[0], result[1] > 0.5) if objects else result

    return render


def jax_render_function(renderer, bases: bool = False, window: tuple[int, int] | None = None) -> Callable:
    """A JAX function params -> image(s) (or bases) that renders with the JAX tracer: no callback,
    the whole likelihood stays a JAX program (on a GPU, on the device).

    Under ``jax.vmap`` a traced shape class would turn the tracer's ``lax.switch``
    over classes into a select that renders every class for every chain; the custom
    vmap rule instead hands the whole batch to the tracer's batched render, which
    renders it as the device prefers (:func:`~mitsuba_p3.render.jax_tracer.batching_for`).
    With ``window`` (height, width) the function is ``render(params, offset)``, as
    :func:`mitsuba_render_function`'s.
    """
    import jax
    import jax.numpy as jnp

    # numpy, not JAX arrays: this may be built while a sampler is being traced (a window's function is
    # made on first use), and a JAX array made then would be that trace's tracer, leaking into the next
    shared = {k: np.asarray(v) for k, v in renderer.params.items() if k not in OBJECT_KEYS}

    def draw(params: dict, offset):
        constants = {k: jnp.asarray(v) for k, v in shared.items()}     # made in the trace that uses them
        return renderer.render_jax({**constants, **params}, bases=bases, window=(offset, window) if window else None)

    render = jax.custom_batching.custom_vmap(draw)

    @render.def_vmap
    def render_batch(axis_size, in_batched, params, offset):
        flags = in_batched[0]
        params = {k: v if flags[k] else jnp.broadcast_to(v, (axis_size,) + jnp.shape(v)) for k, v in params.items()}
        if in_batched[1]:        # the offset belongs to the observation: the same for the whole batch
            offset = offset[0]
        return draw(params, offset), True

    if window:
        return lambda params, offset: render(params, jnp.asarray(offset, jnp.int32))
    return lambda params: render(params, jnp.zeros(2, jnp.int32))
