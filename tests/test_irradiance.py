"""Shading fields on the object's normals (mitsuba_p3.fit.irradiance) and the normals the tracer finds."""
from __future__ import annotations

import numpy as np
import pytest

from mitsuba_p3.fit import fields, irradiance


def _sphere_window(height=24, width=28, radius=9.0):
    """A window with a ball's disc in it: its mask and its normals (orthographic, facing the viewer -y)."""
    rows, cols = np.mgrid[0:height, 0:width].astype(float)
    u, v = (cols - width / 2) / radius, (height / 2 - rows) / radius
    inside = u ** 2 + v ** 2 < 1.0
    normals = np.zeros((height, width, 3))
    normals[..., 2] = 1.0
    depth = np.sqrt(np.clip(1.0 - u ** 2 - v ** 2, 0.0, 1.0))
    normals[inside] = np.stack([u, -depth, v], axis=-1)[inside]
    return inside, normals


def _masks(inside):
    shadow = np.zeros_like(inside)
    shadow[-3:] = ~inside[-3:]
    return np.stack([inside, shadow, ~(inside | shadow)]).astype(float)


def test_the_harmonics_of_a_normal_are_the_nine_of_degree_two():
    n = np.array([0.6, 0.0, 0.8])
    assert np.allclose(irradiance.irradiance_basis(n), [1, 0.6, 0, 0.8, 0, 0, 0.48, 0.36, 3 * 0.64 - 1])
    assert list(irradiance.SH_BANDS) == [0, 1, 1, 1, 2, 2, 2, 2, 2]


def test_without_an_object_the_normal_form_is_the_pixel_form():
    """The floor's regions keep the window's plane; the padded functions add nothing to the density."""
    rng = np.random.default_rng(1)
    inside, normals = _sphere_window()
    masks = _masks(np.zeros_like(inside))
    residual = rng.normal(scale=0.03, size=inside.shape + (3,)) + 0.02
    floor = [0.04, 0.01, 0.05, 0.02]
    pixel = fields.field_log_likelihood(residual, masks, 0.03, fields.column_variances([0.1, 0.1] + floor, 1, "achromatic"),
                                        fields.monomials(*inside.shape, 1), loading=fields.loadings(1, "achromatic"))
    normal = irradiance.log_likelihood(residual, masks, normals, 0.03, [0.1, 0.1, 0.1] + floor, "achromatic")
    assert normal == pytest.approx(pixel, rel=1e-9)


def test_a_balls_shading_is_explained_by_its_own_normals_and_not_by_a_flat_faces():
    """A residual that is a smooth function of a ball's normals (a lamp moved) is likelier under the ball's
    normals than under one flat normal over the same disc (a drum's top seen from above), and likelier than
    under the pixel fields; the fit finds the bands' scales and the white noise's."""
    rng = np.random.default_rng(2)
    inside, normals = _sphere_window()
    masks = _masks(inside)
    windows, normal_maps = [], []
    for _ in range(12):
        weights = rng.normal(size=9) * np.array([0.05, 0.08, 0.08, 0.08, 0.03, 0.03, 0.03, 0.03, 0.03])
        shading = irradiance.irradiance_basis(normals) @ weights * inside
        windows.append(shading[..., None] * np.ones(3) + rng.normal(scale=0.01, size=inside.shape + (3,)))
        normal_maps.append(normals)
    windows, normal_maps = np.stack(windows), np.stack(normal_maps)
    all_masks = np.broadcast_to(masks, (len(windows),) + masks.shape)
    form, _ = irradiance.fit_normal_fields(windows, all_masks, normal_maps, "achromatic")
    assert form.sigma == pytest.approx(0.01, rel=0.1)
    assert np.allclose(form.taus[:3], [0.05, 0.08, 0.03], rtol=0.5)         # the bands' scales drawn above
    flat = np.where(inside[..., None], np.array([0.0, -1.0, 0.0]), normals)
    own = irradiance.log_likelihood(windows, all_masks, normal_maps, form.sigma, form.taus, "achromatic")
    other = irradiance.log_likelihood(windows, all_masks, np.broadcast_to(flat, normal_maps.shape), form.sigma,
                                      form.taus, "achromatic")
    assert np.all(own > other + 50)
    pixel_form, _ = fields.fit_fields(windows, all_masks, 1, "achromatic")
    pixel = fields.field_log_likelihood(windows, all_masks, pixel_form.sigma, pixel_form.variances(),
                                        fields.monomials(*inside.shape, 1), loading=fields.loadings(1, "achromatic"))
    assert own.sum() > pixel.sum()


def test_the_tracer_finds_a_spheres_and_a_cubes_normals():
    import jax.numpy as jnp

    from mitsuba_p3.render.jax_tracer import camera_rays, surface_normals
    from mitsuba_p3.scene import Camera

    origin, rays = camera_rays(Camera(), 60, 80)
    base = {"shift": jnp.array([0.01, 0.02]), "theta": jnp.array(0.3), "scale": jnp.array([0.035] * 3)}
    for kappa, check in ((0, "sphere"), (1, "cube")):
        normal = np.asarray(surface_normals({**base, "kappa": kappa}, jnp.asarray(origin), jnp.asarray(rays), 2.0))
        assert np.allclose(np.linalg.norm(normal, axis=-1), 1.0, atol=1e-5)
        on = ~np.all(np.isclose(normal, [0.0, 0.0, 1.0]), axis=-1)
        assert on.sum() > 50
        if check == "cube":      # every face normal is one of the turned cube's six (or the top's (0, 0, 1))
            c, s = np.cos(0.3), np.sin(0.3)
            faces = np.array([[c, s, 0], [-s, c, 0], [0, 0, 1]])
            assert np.allclose(np.abs(normal[on] @ faces.T).max(axis=-1), 1.0, atol=1e-4)
        else:                    # a sphere's normals point every way towards the camera
            assert normal[on][:, 1].min() < -0.9 and np.ptp(normal[on][:, 0]) > 1.0
