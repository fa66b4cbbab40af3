"""Mitsuba inside JAX: the callback that returns numpy images, and the one that renders into XLA's buffers."""
from __future__ import annotations

import numpy as np
import pytest

from mitsuba_p3.infer.render_functions import in_place_available, mitsuba_render_function
from mitsuba_p3.render import make_renderer
from mitsuba_p3.render.mitsuba import MitsubaRenderer

from .conftest import random_object_params

H, W = 24, 32
WINDOW, OFFSET = (10, 12), (5, 7)

needs_buffer_callback = pytest.mark.skipif(not in_place_available(), reason="this JAX has no buffer_callback")


def test_render_into_writes_the_render_and_the_object_pixels_in_place(scene):
    """render_into fills the caller's arrays (no array returned) with render's and render_bases' values,
    on the whole image and on a window, and refuses an output of the wrong size or type."""
    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    params = random_object_params(np.random.default_rng(0), 3)
    for view in (renderer, renderer.window(*OFFSET, *WINDOW)):
        pixels = (3, view.height, view.width)
        for bases, render in ((False, view.render), (True, view.render_bases)):
            expected, covered = render(params, objects=True)
            image = np.full(pixels + ((4, 3) if bases else (3,)), -1.0, np.float32)
            mask = np.full(pixels, -1.0, np.float32)
            assert view.render_into(params, image, mask, bases=bases) is None
            np.testing.assert_array_equal(image, expected)
            np.testing.assert_array_equal(mask, covered.astype(np.float32))
            assert 0 < covered.sum() < covered.size
    with pytest.raises(ValueError, match="expected"):
        renderer.render_into(params, np.zeros((2, H, W, 3), np.float32))
    with pytest.raises(ValueError, match="float32"):       # a float64 array would be copied, not written
        renderer.render_into(params, np.zeros((3, H, W, 3), np.float64))


@needs_buffer_callback
def test_in_place_gives_the_pure_callbacks_values_without_an_image_through_the_host(scene, monkeypatch):
    """Under jit and vmap, single and batched, whole image and window, image and bases, with and without
    the object's pixels: the in-place path returns exactly the pure_callback path's arrays, and never
    calls the renders that return numpy images."""
    import jax
    import jax.numpy as jnp

    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    params = {k: jnp.asarray(v) for k, v in random_object_params(np.random.default_rng(1), 4).items()}
    single = {k: v[2] for k, v in params.items()}
    for bases in (False, True):
        for objects in (False, True):
            for window in (None, WINDOW):
                results = {}
                for in_place in (False, True):
                    f = mitsuba_render_function(renderer, bases, window, objects, in_place=in_place)
                    g = (lambda p, f=f: f(p, jnp.array(OFFSET))) if window else f
                    with monkeypatch.context() as patch:
                        if in_place:
                            for name in ("render", "render_bases", "_evaluated"):
                                patch.setattr(MitsubaRenderer, name, _refused(name))
                        results[in_place] = jax.tree_util.tree_map(
                            np.asarray, (jax.jit(jax.vmap(g))(params), jax.jit(g)(single)))
                pure, in_place = (jax.tree_util.tree_leaves(results[w]) for w in (False, True))
                assert [a.shape for a in pure] == [b.shape for b in in_place]
                for a, b in zip(pure, in_place):
                    assert a.dtype == b.dtype
                    np.testing.assert_array_equal(a, b)
                assert np.ptp(pure[0]) > 0.1        # real renders, not two arrays of zeros


def test_the_default_follows_the_device(scene, monkeypatch):
    """On the CPU the default is pure_callback (render_into is not called); where Mitsuba renders on
    a GPU (``on_device``) and JAX has buffer_callback, it renders in place."""
    import jax
    import jax.numpy as jnp

    renderer = make_renderer(scene, height=H, width=W)
    assert renderer.on_device is False
    params = {k: jnp.asarray(v) for k, v in random_object_params(np.random.default_rng(2), 2).items()}
    monkeypatch.setattr(MitsubaRenderer, "render_into", _refused("render_into"))
    expected = np.asarray(jax.jit(jax.vmap(mitsuba_render_function(renderer)))(params))
    if not in_place_available():
        return
    monkeypatch.setattr(MitsubaRenderer, "on_device", property(lambda self: True))
    with pytest.raises(Exception, match="render_into was called"):
        jax.block_until_ready(jax.jit(jax.vmap(mitsuba_render_function(renderer)))(params))
    monkeypatch.undo()
    monkeypatch.setattr(MitsubaRenderer, "on_device", property(lambda self: True))
    np.testing.assert_array_equal(np.asarray(jax.jit(jax.vmap(mitsuba_render_function(renderer)))(params)), expected)


@pytest.mark.gpu
def test_on_a_gpu_mitsuba_renders_into_xlas_device_buffers(scene):
    """With Mitsuba on CUDA the default renders into XLA's device buffers, with pure_callback's values."""
    import jax
    import jax.numpy as jnp

    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    if not renderer.on_device or jax.default_backend() != "gpu":
        pytest.skip("needs Mitsuba's cuda_ad_rgb and JAX on a GPU")
    params = {k: jnp.asarray(v) for k, v in random_object_params(np.random.default_rng(3), 8).items()}
    for bases in (False, True):
        pure = jax.jit(jax.vmap(mitsuba_render_function(renderer, bases, None, True, in_place=False)))(params)
        kept = jax.jit(jax.vmap(mitsuba_render_function(renderer, bases, None, True)))(params)
        for a, b in zip(pure, kept):
            np.testing.assert_array_equal(np.asarray(a), np.asarray(b))


def _refused(name):
    def refuse(*args, **kwargs):
        raise AssertionError(f"{name} was called")
    return refuse
