"""Dr.Jit gradients of an image loss against central finite differences.

For each differentiable parameter we compare the directional derivative along a
random direction v: <grad L, v> from the renderer's VJP against
(L(x + h v) - L(x - h v)) / 2h, with L = sum(image * cotangent).
"""
from __future__ import annotations

import numpy as np
import pytest

from mitsuba_p3.render import make_renderer
from mitsuba_p3.render.contract import DIFFERENTIABLE_KEYS

H, W = 48, 64
STEP = {"light_position": 2e-3, "shininess": 0.05, "floor_shininess": 0.05}


@pytest.fixture(scope="module")
def setup():
    from mitsuba_p3.scene import load_scene

    from .conftest import SCENES

    scene = load_scene(SCENES / "room.xml", {"shape": "sphere", "specular": "0.6", "shininess": "12",
                                             "scale": "0.06, 0.05, 0.05"})
    scene.floor.material.specular = 0.3
    scene.floor.material.shininess = 6.0
    scene.sky, scene.ground = np.array([0.12, 0.14, 0.16]), np.array([0.08, 0.07, 0.06])   # the hemisphere term on
    renderer = make_renderer(scene, height=H, width=W)
    rng = np.random.default_rng(0)
    cotangent = rng.normal(size=(H, W, 3)).astype(np.float32)
    return renderer, cotangent, rng


def _loss(renderer, params, cotangent) -> float:
    return float(np.sum(renderer.render(params).astype(np.float64) * cotangent))


@pytest.fixture(scope="module")
def setup_ggx():
    """The same world with the GGX microfacet lobe (render/lobes.py; no hemisphere term there)."""
    from mitsuba_p3.scene import load_scene

    from .conftest import SCENES

    scene = load_scene(SCENES / "room.xml", {"shape": "sphere", "specular": "0.3", "shininess": "12",
                                             "scale": "0.06, 0.05, 0.05"}).replace(lobe="ggx")
    scene.floor.material.specular = 0.2
    scene.floor.material.shininess = 6.0
    rng = np.random.default_rng(1)
    return make_renderer(scene, height=H, width=W), rng.normal(size=(H, W, 3)).astype(np.float32), rng


GGX_KEYS = ("colour", "specular", "shininess", "light_position", "light_intensity", "floor_specular",
            "floor_shininess")


@pytest.mark.parametrize("lobe, key", [("phong", k) for k in DIFFERENTIABLE_KEYS] + [("ggx", k) for k in GGX_KEYS])
def test_gradient_matches_central_differences(request, lobe, key):
    renderer, cotangent, rng = request.getfixturevalue("setup" if lobe == "phong" else "setup_ggx")
    base = renderer.params
    grads = renderer.vjp(None, cotangent)
    assert set(grads) >= set(DIFFERENTIABLE_KEYS)
    value = base[key]
    direction = rng.normal(size=np.shape(value)).astype(np.float32)
    direction /= np.linalg.norm(direction)
    h = STEP.get(key, 1e-2)
    plus = _loss(renderer, {key: value + h * direction}, cotangent)
    minus = _loss(renderer, {key: value - h * direction}, cotangent)
    numeric = (plus - minus) / (2 * h)
    analytic = float(np.sum(grads[key] * direction))
    assert abs(numeric) > 1e-2, f"{key}: the loss barely depends on it; the check would be vacuous"
    assert analytic == pytest.approx(numeric, rel=0.03, abs=1e-3), f"{key}: AD {analytic} vs FD {numeric}"


def test_gradients_are_batched(setup):
    """Object-parameter gradients of a batch are per element; global ones are summed."""
    renderer, _, rng = setup
    from .conftest import random_object_params

    params = random_object_params(rng, 3)
    cotangent = rng.normal(size=(3, H, W, 3)).astype(np.float32)
    grads = renderer.vjp(params, cotangent)
    assert grads["colour"].shape == (3, 3) and grads["light_position"].shape == (3, 3)
    single = renderer.vjp({k: v[1] for k, v in params.items()}, cotangent[1])
    np.testing.assert_allclose(grads["colour"][1], single["colour"], rtol=1e-4, atol=1e-4)
