"""The JAX tracer: the same contract as Mitsuba, agreement with it, gradients, batching."""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from mitsuba_p3.render import make_renderer
from mitsuba_p3.render.crosscheck import agreement, interior_mask
from mitsuba_p3.scene import load_scene

from .conftest import SCENES, random_object_params

H, W = 60, 80


def test_camera_rays_match_mitsubas_sensor(mi):
    from mitsuba_p3.render.jax_tracer import camera_rays
    from mitsuba_p3.render.phong import pixel_centre_rays

    scene = load_scene(SCENES / "fsclvr.xml")
    sensor = mi.load_dict({"type": "perspective", "fov": scene.camera.fov, "fov_axis": "y",
                           "to_world": mi.ScalarTransform4f().look_at(origin=scene.camera.origin.tolist(),
                                                                      target=scene.camera.target.tolist(),
                                                                      up=scene.camera.up.tolist()),
                           "film": {"type": "hdrfilm", "width": W, "height": H}})
    expected = np.asarray(pixel_centre_rays(sensor).d).T
    origin, directions = camera_rays(scene.camera, H, W)
    np.testing.assert_allclose(directions, expected, atol=2e-6)
    np.testing.assert_allclose(origin, scene.camera.origin, atol=1e-7)


def _cases():
    rng = np.random.default_rng(11)
    cases = []
    for shape in ("sphere", "cube", "cylinder"):
        for pose in range(3):
            for lights in (1, 3):
                for shadows in (False, True):
                    cases.append((shape, pose, lights, shadows, int(rng.integers(1 << 30))))
    return cases


@pytest.mark.parametrize("shape, pose, lights, shadows, seed", _cases(),
                         ids=[f"{c[0]}-pose{c[1]}-{c[2]}lights-{'shadows' if c[3] else 'noshadows'}" for c in _cases()])
def test_agrees_with_mitsuba(shape, pose, lights, shadows, seed):
    rng = np.random.default_rng(seed)
    scene = load_scene(SCENES / "room.xml", {"shape": shape})
    scene.lights = scene.lights[:lights]
    params = {k: v[0] for k, v in random_object_params(rng, 1).items()}
    params["kappa"] = np.int32(["sphere", "cube", "cylinder"].index(shape))
    images, ids = [], []
    for kind in ("mitsuba", "jax"):
        renderer = make_renderer(scene, kind, height=120, width=160, shadows=shadows)
        images.append(renderer.render(params))
        ids.append(renderer.surface_ids(params))
    figures = agreement(images[0], images[1], ids[0], ids[1])
    assert (ids[0] == 2).sum() > 20, "the object must be in view for the check to mean anything"
    assert figures["psnr_interior_db"] >= 40, figures
    assert figures["fraction_over_2_255"] <= 0.005, figures


def _assert_renderers_agree(scene, params) -> np.ndarray:
    """Mitsuba's and the JAX tracer's renders of ``params`` in ``scene`` at 120x160 agree (>= 40 dB inside the
    surfaces, at most 0.5% of pixels off by more than 2/255); returns the JAX render."""
    images, ids = [], []
    for kind in ("mitsuba", "jax"):
        renderer = make_renderer(scene, kind, height=120, width=160)
        images.append(renderer.render(params))
        ids.append(renderer.surface_ids(params))
    figures = agreement(images[0], images[1], ids[0], ids[1])
    assert figures["psnr_interior_db"] >= 40, figures
    assert figures["fraction_over_2_255"] <= 0.005, figures
    return images[1]


@pytest.mark.parametrize("shape", ["cube"])   # the disc's samples are shape-independent; one class suffices
def test_soft_shadows_agree_with_mitsuba(shape):
    """Lights widened into discs: both renderers trace the same fixed sample points (>= 40 dB)."""
    rng = np.random.default_rng(7)
    scene = load_scene(SCENES / "room.xml", {"shape": shape}).replace(shadows=True, light_radius=0.03)
    params = {k: v[0] for k, v in random_object_params(rng, 1).items()}
    params["kappa"] = np.int32(["sphere", "cube", "cylinder"].index(shape))
    assert make_renderer(scene, "jax", height=120, width=160).shadow_samples > 1
    image = _assert_renderers_agree(scene, params)
    hard = make_renderer(scene.replace(light_radius=0.0), "jax", height=120, width=160).render(params)
    assert np.abs(image - hard).max() > 0.01, "the penumbra must differ from the hard shadow"


def test_light_falloff_agrees_with_mitsuba():
    """Inverse-square light falloff (render/falloff.py): one formula in both renderers (>= 40 dB), and it changes
    the image (a light nearer the floor than the reference distance brightens it)."""
    rng = np.random.default_rng(9)
    scene = load_scene(SCENES / "room.xml", {"shape": "cylinder"}).replace(shadows=True, light_falloff=0.5)
    params = {k: v[0] for k, v in random_object_params(rng, 1).items()}
    params["kappa"] = np.int32(2)
    image = _assert_renderers_agree(scene, params)
    none = make_renderer(scene.replace(light_falloff=0.0), "jax", height=120, width=160).render(params)
    assert np.abs(image - none).max() > 0.02, "the falloff must change the image"


@pytest.mark.parametrize("shape", ["sphere", "cube", "cylinder"])
def test_the_hemisphere_term_agrees_with_mitsuba(shape):
    """A sky and ground (render/hemisphere.py): one formula in both renderers (>= 40 dB), on a shiny object."""
    rng = np.random.default_rng(8)
    scene = load_scene(SCENES / "room.xml", {"shape": shape}).replace(
        shadows=True, sky=np.array([0.3, 0.35, 0.4]), ground=np.array([0.2, 0.15, 0.1]))
    params = {k: v[0] for k, v in random_object_params(rng, 1).items()}
    params.update(kappa=np.int32(["sphere", "cube", "cylinder"].index(shape)), specular=np.float32(0.7))
    _assert_renderers_agree(scene, params)


def test_a_window_renders_exactly_its_crop(pair):
    """render_jax with a window (traced offset, static size) is that crop of the whole image, batched or not."""
    renderer = pair["jax"]
    params = random_object_params(np.random.default_rng(9), 3)
    full = {k: jnp.asarray(v) for k, v in renderer.merged(params).items()}
    whole = np.asarray(renderer.render_jax(full))
    crop = jax.jit(lambda p, offset: renderer.render_jax(p, window=(offset, (20, 30))))
    for top, left in ((0, 0), (7, 11)):
        np.testing.assert_allclose(np.asarray(crop(full, jnp.array([top, left]))), whole[:, top:top + 20, left:left + 30],
                                   atol=1e-6)
    single = {k: (v[0] if k in params else v) for k, v in full.items()}
    np.testing.assert_allclose(np.asarray(renderer.render_jax(single, window=(jnp.array([7, 11]), (20, 30)))),
                               whole[0, 7:27, 11:41], atol=1e-6)


def test_interior_mask_excludes_silhouettes():
    ids = np.zeros((7, 7), int)
    ids[2:5, 2:5] = 2
    mask = interior_mask(ids, ids)
    assert mask[3, 3] and not mask[2, 2] and not mask[1, 3] and mask[0, 0]
    other = ids.copy()
    other[3, 3] = 1
    assert not interior_mask(ids, other)[3, 3]


@pytest.mark.parametrize("shape", ["sphere", "cube", "cylinder"])
def test_the_ggx_lobe_agrees_with_mitsuba(shape):
    """The GGX microfacet lobe (render/lobes.py): one formula in both renderers (>= 40 dB), on a shiny object."""
    rng = np.random.default_rng(9)
    scene = load_scene(SCENES / "room.xml", {"shape": shape}).replace(shadows=True, lobe="ggx")
    params = {k: v[0] for k, v in random_object_params(rng, 1).items()}
    params.update(kappa=np.int32(["sphere", "cube", "cylinder"].index(shape)), specular=np.float32(0.5),
                  shininess=np.float32(30.0))
    images, ids = [], []
    for kind in ("mitsuba", "jax"):
        renderer = make_renderer(scene, kind, height=120, width=160)
        images.append(renderer.render(params))
        ids.append(renderer.surface_ids(params))
    assert (ids[0] == 2).sum() > 20, "the object must be in view for the check to mean anything"
    figures = agreement(images[0], images[1], ids[0], ids[1])
    assert figures["psnr_interior_db"] >= 40, figures
    assert figures["fraction_over_2_255"] <= 0.005, figures


@pytest.fixture(scope="module")
def pair():
    scene = load_scene(SCENES / "room.xml", {"specular": "0.5", "shininess": "10", "scale": "0.05"})
    return {kind: make_renderer(scene, kind, height=H, width=W) for kind in ("mitsuba", "jax")}


@pytest.fixture(scope="module")
def pair_with_environment():
    scene = load_scene(SCENES / "room.xml", {"specular": "0.5", "shininess": "10", "scale": "0.05"}).replace(
        sky=np.array([0.12, 0.14, 0.16]), ground=np.array([0.08, 0.07, 0.06]))
    return {kind: make_renderer(scene, kind, height=H, width=W) for kind in ("mitsuba", "jax")}


@pytest.mark.parametrize("key", ["colour", "light_intensity", "diffuse", "light_position", "floor_pattern", "sky",
                                 "ground"])
def test_gradients_agree_with_mitsuba(pair, key, request):
    if key in ("sky", "ground"):      # the hemisphere term is traced only in a world that has an environment
        pair = request.getfixturevalue("pair_with_environment")
    cotangent = np.random.default_rng(5).normal(size=(H, W, 3)).astype(np.float32)
    g_mi = pair["mitsuba"].vjp(None, cotangent)[key]
    g_jax = pair["jax"].vjp(None, cotangent)[key]
    assert np.linalg.norm(g_mi) > 1e-3
    assert np.linalg.norm(g_jax - g_mi) <= 0.01 * np.linalg.norm(g_mi), (key, g_mi.ravel()[:6], g_jax.ravel()[:6])


def test_jax_grad_of_a_pure_loss(pair):
    """render_jax is a pure JAX function: jax.grad and jit work on it directly."""
    renderer = pair["jax"]
    params = {k: jnp.asarray(v) for k, v in renderer.params.items()}
    target = jnp.asarray(renderer.render({"colour": np.array([0.2, 0.6, 0.3], np.float32)}))

    def loss(colour):
        return jnp.mean((renderer.render_jax({**params, "colour": colour}) - target) ** 2)

    grad = jax.jit(jax.grad(loss))(params["colour"])
    assert np.all(np.isfinite(np.asarray(grad))) and np.linalg.norm(np.asarray(grad)) > 0
    step = params["colour"] - 0.5 * grad / jnp.linalg.norm(grad) * 0.05
    assert loss(step) < loss(params["colour"])


def test_batch_equals_singles_and_vmap(pair):
    """A batch renders each of its images as a single render does: to float32 rounding (1e-5; on a GPU
    XLA fuses a vmapped batch's arithmetic differently, 5e-6 apart on an H200, results/gpu/)."""
    renderer = pair["jax"]
    params = random_object_params(np.random.default_rng(4), 6)
    batch = renderer.render(params)
    for b in range(6):
        np.testing.assert_allclose(batch[b], renderer.render({k: v[b] for k, v in params.items()}), atol=1e-5)
    full = {k: jnp.asarray(v) for k, v in renderer.merged(params).items()}
    objects = {k: full[k] for k in params}
    shared = {k: v for k, v in full.items() if k not in params}
    vmapped = jax.vmap(lambda obj: renderer.render_jax({**shared, **obj}))(objects)
    np.testing.assert_allclose(np.asarray(vmapped), batch, atol=1e-5)


def test_both_batchings_render_the_same(pair, monkeypatch):
    """The GPU's vmap batching and the CPU's map batching are one model (run here on the CPU)."""
    from mitsuba_p3.render.jax_tracer import BATCHING_ENV, JaxRenderer

    params = random_object_params(np.random.default_rng(5), 5)
    images = {}
    for mode in ("map", "vmap"):
        monkeypatch.setenv(BATCHING_ENV, mode)
        renderer = JaxRenderer(pair["jax"].scene, height=pair["jax"].height, width=pair["jax"].width)
        assert renderer.batching == mode
        images[mode] = renderer.render(params)
        images[mode + "_bases"] = renderer.render_bases(params)
    np.testing.assert_allclose(images["vmap"], images["map"], atol=1e-5)
    np.testing.assert_allclose(images["vmap_bases"], images["map_bases"], atol=1e-5)


def test_cli_crosscheck(tmp_path):
    import json
    import subprocess
    import sys

    done = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "crosscheck", str(SCENES / "fsclvr.xml"),
                           "--shape", "cube", "--shadows", "--resolution", "60x80", "-o", str(tmp_path / "d.png")],
                          capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    figures = json.loads(done.stdout)
    assert figures["psnr_interior_db"] >= 40 and (tmp_path / "d.png").exists()


@pytest.mark.parametrize("shadows", [False, True])
def test_material_bases_rebuild_the_image(shadows):
    """render_bases: clip(c (k_a A + k_d D) + k_s S + F) is the render, in both renderers, which agree."""
    scene = load_scene(SCENES / "room.xml")
    params = random_object_params(np.random.default_rng(8), 6)
    bases = {}
    for kind in ("mitsuba", "jax"):
        renderer = make_renderer(scene, kind, height=H, width=W, shadows=shadows)
        image, b = renderer.render(params), renderer.render_bases(params)
        assert b.shape == (6, H, W, 4, 3)
        c = params["colour"][:, None, None]
        ka, kd, ks = (params[k][:, None, None, None] for k in ("ambient", "diffuse", "specular"))
        rebuilt = np.clip(c * (ka * b[..., 0, :] + kd * b[..., 1, :]) + ks * b[..., 2, :] + b[..., 3, :], 0, 1)
        np.testing.assert_allclose(rebuilt, image, atol=1e-5)
        on_object = renderer.surface_ids(params) == 2
        assert on_object.sum() > 50 and np.all(b[..., 3, :][on_object] == 0)
        assert np.all(b[..., :3, :][~on_object] == 0)
        np.testing.assert_allclose(renderer.render_bases({k: v[1] for k, v in params.items()}), b[1], atol=1e-6)
        bases[kind] = b
    ids = make_renderer(scene, "jax", height=H, width=W, shadows=shadows).surface_ids(params)
    interior = np.stack([interior_mask(i, i) for i in ids])
    np.testing.assert_allclose(bases["mitsuba"][interior], bases["jax"][interior], atol=1e-3)


@pytest.mark.gpu
@pytest.mark.skipif(jax.default_backend() != "gpu", reason="needs JAX on a GPU")
def test_on_a_gpu_batches_are_one_vmap_launch_and_match_the_cpu_model(pair):
    """Where JAX runs on a GPU the tracer batches with vmap by default, and its images are the
    model's (rendered again with map batching on the same device)."""
    import os

    from mitsuba_p3.render.jax_tracer import BATCHING_ENV, JaxRenderer

    renderer = JaxRenderer(pair["jax"].scene, height=pair["jax"].height, width=pair["jax"].width)
    assert renderer.batching == "vmap"
    params = random_object_params(np.random.default_rng(6), 16)
    os.environ[BATCHING_ENV] = "map"
    try:
        mapped = JaxRenderer(pair["jax"].scene, height=renderer.height, width=renderer.width).render(params)
    finally:
        del os.environ[BATCHING_ENV]
    np.testing.assert_allclose(renderer.render(params), mapped, atol=1e-5)
