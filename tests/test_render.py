"""The Mitsuba renderer against the contract, Mitsuba's own integrator path, and itself."""
from __future__ import annotations

import numpy as np
import pytest

from mitsuba_p3.errors import SceneError
from mitsuba_p3.render import make_renderer
from mitsuba_p3.scene import load_scene

from .conftest import SCENES, random_object_params

H, W = 60, 80


def test_contract_single_and_batched(scene):
    renderer = make_renderer(scene, height=H, width=W)
    image = renderer.render()
    assert image.shape == (H, W, 3) and image.dtype == np.float32
    assert 0.0 <= image.min() and image.max() <= 1.0
    batch = renderer.render(random_object_params(np.random.default_rng(0), 4))
    assert batch.shape == (4, H, W, 3) and batch.dtype == np.float32


def test_batch_equals_single_renders(scene):
    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    params = random_object_params(np.random.default_rng(1), 6)
    batch = renderer.render(params)
    for b in range(6):
        single = renderer.render({k: v[b] for k, v in params.items()})
        np.testing.assert_allclose(batch[b], single, atol=1e-6, err_msg=f"batch element {b}")
    assert np.abs(batch[0] - batch[1]).max() > 0.1  # the batch elements really differ


def test_a_window_renders_exactly_its_crop_of_the_image(scene):
    """A window view renders only its pixels, and they are the full image's (colours and bases,
    with shadows, batched); a window outside the image is refused."""
    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    params = random_object_params(np.random.default_rng(3), 3)
    view = renderer.window(10, 24, 32, 40)
    np.testing.assert_array_equal(view.render(params), renderer.render(params)[:, 10:42, 24:64])
    np.testing.assert_array_equal(view.render_bases(params), renderer.render_bases(params)[:, 10:42, 24:64])
    assert renderer.render().shape == (H, W, 3)           # the full renderer is untouched
    with pytest.raises(SceneError, match="does not fit"):
        renderer.window(40, 0, 32, 40)


def test_render_is_deterministic(scene):
    renderer = make_renderer(scene, height=H, width=W)
    assert np.array_equal(renderer.render(), renderer.render())


@pytest.mark.parametrize("shape", ["sphere", "cube", "cylinder"])
@pytest.mark.parametrize("shadows", [False, True])
def test_matches_mitsubas_own_scene_loading(mi, shape, shadows):
    """The ray-space renderer equals mi.load_file + phong_integrator (instances, Embree) on the XML."""
    overrides = {"shape": shape, "theta_deg": "35", "scale": "0.04, 0.025, 0.03", "shift_x": "0.02",
                 "shift_y": "-0.01"}
    scene = load_scene(SCENES / "room.xml", overrides)
    fast = make_renderer(scene, height=120, width=160, shadows=shadows).render()
    mi_scene = mi.load_file(str(SCENES / "room.xml"), **overrides)
    sensor = mi_scene.sensors()[0]
    params = mi.traverse(sensor)
    params["film.size"] = [160, 120]
    params.update()
    integrator = mi.load_dict({"type": "phong_integrator", "shadows": shadows})
    reference = mi.render(mi_scene, integrator=integrator).numpy()
    diff = np.abs(fast - reference).max(axis=2)
    assert (diff > 2 / 255).mean() <= 0.005, f"{(diff > 2 / 255).mean():.4%} of pixels differ"
    assert np.median(diff) < 1e-4


def test_image_orientation(scene):
    """+x is to the right, +y (away from the camera) is higher up, row 0 is the top."""
    renderer = make_renderer(scene, height=H, width=W)
    floor_only = renderer.render({"scale": np.full(3, 1e-4, np.float32)})

    def centroid(image):
        mask = np.abs(image - floor_only).max(axis=2) > 0.02
        rows, cols = np.nonzero(mask)
        return rows.mean(), cols.mean()

    r0, c0 = centroid(renderer.render())
    r_right, c_right = centroid(renderer.render({"shift": np.array([0.08, 0.0], np.float32)}))
    r_far, c_far = centroid(renderer.render({"shift": np.array([0.0, 0.08], np.float32)}))
    assert c_right > c0 + 5 and abs(r_right - r0) < 3
    assert r_far < r0 - 3


def test_shadows_only_darken(scene):
    lit = make_renderer(scene, height=H, width=W, shadows=False).render()
    shadowed = make_renderer(scene, height=H, width=W, shadows=True).render()
    assert np.all(shadowed <= lit + 1e-6)
    assert (lit - shadowed).max() > 0.05  # a visible cast shadow exists


def test_shadow_rays_in_closed_form_agree_with_mitsubas_scene(scene):
    """The closed-form occlusion of shadow rays gives Mitsuba's answer (the object's parts in its
    scene, through Embree) for rays from points around objects of every class, pose and size, whose
    segments end before, inside or past the object: all but grazing rays agree."""
    import drjit as dr

    from mitsuba_p3.backend import mitsuba

    mi = mitsuba()
    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    rng = np.random.default_rng(7)
    n = 60_000
    params = random_object_params(rng, n)
    p = renderer._to_drjit_cached(renderer.merged(params))
    frame = renderer._object_frame(p, dr.arange(mi.UInt32, n))
    # origins in a box about the object, directions towards points near it, lengths short and long
    centre = np.concatenate([params["shift"], params["scale"][:, 2:]], axis=1)
    origin = centre + rng.uniform(-3, 3, (n, 3)) * params["scale"].max(1, keepdims=True)
    origin[:, 2] = np.abs(origin[:, 2])
    target = centre + rng.normal(0, 1.0, (n, 3)) * params["scale"]
    direction = (target - origin) / np.linalg.norm(target - origin, axis=1, keepdims=True)
    reach = rng.choice([0.3, 1.0, 10.0], n) * np.linalg.norm(target - origin, axis=1)
    args = (frame, mi.Point3f(*origin.T.astype(np.float32)), mi.Vector3f(*direction.T.astype(np.float32)),
            mi.Float(reach.astype(np.float32)))
    closed = renderer._occluded(*args).numpy()
    # Mitsuba's answer: the first hit of the whole ray, blocking when it lies within reach (its
    # ray test alone also blocks rays whose segment ends before the sphere: not a shadow ray's case)
    hit, distance, _ = renderer._trace_object(*args[:3])
    traced = hit.numpy() & (distance.numpy() <= reach)
    # rays that start inside the object are not shadow rays: leave them out
    c, s = np.cos(params["theta"]), np.sin(params["theta"])
    x, y = origin[:, 0] - params["shift"][:, 0], origin[:, 1] - params["shift"][:, 1]
    local = np.stack([c * x + s * y, -s * x + c * y, origin[:, 2]], axis=1) / params["scale"]
    inside = np.select([params["kappa"] == 0, params["kappa"] == 1],
                       [np.linalg.norm(local - [0, 0, 1], axis=1) < 1, np.abs(local - [0, 0, 1]).max(1) < 1],
                       (np.hypot(local[:, 0], local[:, 1]) < 1) & (np.abs(local[:, 2] - 1) < 1))
    assert 0.2 < closed[~inside].mean() < 0.8, "the rays are not a fair mix of blocked and free"
    for kappa in range(3):
        mine = (params["kappa"] == kappa) & ~inside
        assert (closed[mine] != traced[mine]).mean() < 1e-3, f"class {kappa}"


def test_soft_shadows_lie_between_lit_and_hard(scene):
    """A light with a radius casts a penumbra: never darker than the hard shadow's umbra nor
    brighter than no shadow, with pixels strictly between; radius 0 is the hard shadow exactly."""
    lit = make_renderer(scene, height=H, width=W, shadows=False).render()
    hard = make_renderer(scene, height=H, width=W, shadows=True).render()
    soft_scene = scene.replace(light_radius=0.04)
    soft = make_renderer(soft_scene, height=H, width=W, shadows=True)
    assert soft.shadow_samples > 1
    image = soft.render()
    assert np.all(image <= lit + 1e-6) and np.all(image >= hard.min() - 1e-6)
    between = (image > hard + 0.01) & (image < lit - 0.01)
    assert between.any(axis=2).sum() > 20
    assert np.array_equal(soft.render({"light_radius": np.float32(0.0)}), hard)
    assert np.array_equal(soft.render(), image)  # a fixed pattern: deterministic
    wider = soft.render({"light_radius": np.float32(0.08)})
    assert np.abs(wider - image).max() > 0.01


def test_light_falloff_is_inverse_square(scene):
    """With light_falloff d0, a floor point lit by one light straight above it at height h receives (d0 / h)^2
    of the light's diffuse term without falloff; d0 = 0 is the paper's light exactly."""
    from mitsuba_p3.scene import PointLight

    height = 0.4
    one = scene.replace(lights=[PointLight(np.array([0.15, 0.1, height]), np.array([0.3, 0.3, 0.3]))],
                        ambient_light=np.zeros(3), shadows=False)
    renderer = make_renderer(one, height=H, width=W)
    plain = renderer.render()
    assert np.array_equal(renderer.render({"light_falloff": np.float32(0.0)}), plain)
    point = make_renderer(one.replace(light_falloff=0.2), height=H, width=W)
    assert point.falloff and not renderer.falloff
    for made, value in ((renderer, 0.2), (point, 0.0)):   # fixed at construction: a call cannot switch it
        with pytest.raises(SceneError, match="light_falloff"):
            made.render({"light_falloff": np.float32(value)})
    image = point.render()
    # the pixel that sees the floor point under the light: where the unfalloffed render is brightest
    row, col = np.unravel_index(np.argmax(plain.sum(axis=2)), plain.shape[:2])
    assert image[row, col].sum() == pytest.approx(plain[row, col].sum() * (0.2 / height) ** 2, rel=0.03)
    # the farther floor falls off faster than the point under the light
    assert (image / np.maximum(plain, 1e-6))[plain.sum(axis=2) > 0.05].min() < (0.2 / height) ** 2


def _mitsubas_own_render(mi, xml) -> np.ndarray:
    """A saved scene XML rendered by mi.load_file + its phong_integrator (Embree, instances) at 120x160."""
    mi_scene = mi.load_file(str(xml))
    params = mi.traverse(mi_scene.sensors()[0])
    params["film.size"] = [160, 120]
    params.update()
    return mi.render(mi_scene).numpy()


def test_soft_shadows_match_mitsubas_own_integrator(mi, tmp_path):
    """The plugin (phong_integrator with light_radius, through Embree on the XML) and the renderer agree."""
    from mitsuba_p3.scene import save_scene

    scene = load_scene(SCENES / "room.xml", {"shape": "cube", "theta_deg": "20"}).replace(shadows=True,
                                                                                         light_radius=0.03)
    save_scene(scene, tmp_path / "soft.xml")
    assert load_scene(tmp_path / "soft.xml").light_radius == pytest.approx(0.03)
    fast = make_renderer(scene, height=120, width=160).render()
    diff = np.abs(fast - _mitsubas_own_render(mi, tmp_path / "soft.xml")).max(axis=2)
    assert (diff > 2 / 255).mean() <= 0.01, f"{(diff > 2 / 255).mean():.4%} of pixels differ"


def test_light_falloff_matches_mitsubas_own_integrator(mi, tmp_path):
    """The plugin (phong_integrator with light_falloff, through Embree on the XML) and the renderer agree, and
    the saved XML keeps the falloff."""
    from mitsuba_p3.scene import save_scene

    scene = load_scene(SCENES / "room.xml", {"shape": "sphere"}).replace(shadows=True, light_falloff=0.5)
    save_scene(scene, tmp_path / "falloff.xml")
    assert load_scene(tmp_path / "falloff.xml").light_falloff == pytest.approx(0.5)
    fast = make_renderer(scene, height=120, width=160).render()
    plain = make_renderer(scene.replace(light_falloff=0.0), height=120, width=160).render()
    assert np.abs(fast - plain).max() > 0.02
    diff = np.abs(fast - _mitsubas_own_render(mi, tmp_path / "falloff.xml")).max(axis=2)
    assert (diff > 2 / 255).mean() <= 0.01, f"{(diff > 2 / 255).mean():.4%} of pixels differ"


def test_disc_pattern():
    from mitsuba_p3.render.soft_shadows import disc_pattern, samples_for

    assert np.array_equal(disc_pattern(1), np.zeros((1, 2)))
    points = disc_pattern(16)
    radius = np.hypot(points[:, 0], points[:, 1])
    assert points.shape == (16, 2) and radius.max() < 1 and len(np.unique(points.round(4), axis=0)) == 16
    assert abs(points.mean(axis=0)).max() < 0.1  # spread around the centre
    assert samples_for(0.0) == 1 and samples_for(0.02) == 16 and samples_for(0.0, 4) == 4
    with pytest.raises(ValueError):
        disc_pattern(0)


def test_shapes_look_different(scene):
    renderer = make_renderer(scene, height=H, width=W)
    images = [renderer.render({"kappa": np.int32(k), "theta": np.float32(0.4)}) for k in range(3)]
    for a in range(3):
        for b in range(a + 1, 3):
            assert np.abs(images[a] - images[b]).max() > 0.1


def test_no_kernel_recompilation_after_first_render(scene):
    import drjit as dr

    renderer = make_renderer(scene, height=H, width=W, shadows=True)
    rng = np.random.default_rng(2)
    renderer.render({k: v[0] for k, v in random_object_params(rng, 1).items()})
    renderer.render(random_object_params(rng, 5))
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    try:
        for _ in range(5):
            renderer.render({k: v[0] for k, v in random_object_params(rng, 1).items()}
                            | {"light_intensity": rng.uniform(0.1, 0.6, (3, 3)).astype(np.float32)})
            renderer.render(random_object_params(rng, 5))
        history = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    compiled = [k for k in history if str(k["type"]).endswith("JIT") and not k["cache_hit"]]
    assert not compiled, f"{len(compiled)} kernels were compiled after warm-up"
    assert any(str(k["type"]).endswith("JIT") for k in history)  # the history really recorded launches


def _rss_mb() -> float:
    with open("/proc/self/statm") as f:
        return int(f.read().split()[1]) * 4096 / 2**20


@pytest.mark.slow
def test_memory_flat_over_thousands_of_renders(scene):
    """2,200 renders leave the resident memory flat (a leak check: behind ``slow``)."""
    renderer = make_renderer(scene, height=30, width=40)
    rng = np.random.default_rng(3)
    params = [random_object_params(rng, 4) for _ in range(8)]
    for i in range(200):
        renderer.render(params[i % 8])
    before = _rss_mb()
    for i in range(2000):
        renderer.render(params[i % 8])
    grown = _rss_mb() - before
    assert grown < 25, f"resident memory grew by {grown:.1f} MB over 2000 renders"


@pytest.mark.parametrize("update, message", [
    ({"colour": np.array([np.nan, 0.5, 0.5], np.float32)}, "NaN"),
    ({"shift": np.zeros(3, np.float32)}, "shape"),
    ({"kappa": np.int32(5)}, "kappa"),
    ({"kappa": np.float32(0.5)}, "whole number"),
    ({"scale": np.array([0.01, -0.01, 0.01], np.float32)}, "positive"),
    ({"light_intensity": np.ones((2, 3), np.float32)}, "light_position"),
    ({"light_radius": np.float32(-0.01)}, "light_radius"),
    ({"light_falloff": np.float32(-0.1)}, "light_falloff"),
    ({"colur": np.ones(3, np.float32)}, "unknown renderer parameter"),
])
def test_bad_parameters_raise(scene, update, message):
    renderer = make_renderer(scene, height=H, width=W)
    with pytest.raises(SceneError, match=message):
        renderer.render(update)


def test_a_render_over_the_memory_limit_is_refused_before_allocation(scene, monkeypatch):
    """20000x20000 used to take 11.7 GB and a minute before anything was said."""
    from mitsuba_p3.errors import SceneError
    from mitsuba_p3.render import make_renderer

    monkeypatch.setenv("MITSUBA_P3_MEMORY_GB", "0.01")                 # 10 MB: one 120x160 image fits
    renderer = make_renderer(scene, "mitsuba", height=120, width=160)
    assert renderer.render().shape == (120, 160, 3)
    with pytest.raises(SceneError, match="needs about .* GB, over the limit"):
        renderer.render({"shift": np.zeros((64, 2), np.float32)})        # a batch of 64 does not
    with pytest.raises(SceneError, match="MITSUBA_P3_MEMORY_GB"):
        make_renderer(scene, "mitsuba", height=2000, width=2000)


def test_the_hemisphere_term_matches_mitsubas_own_integrator_and_vanishes_without_sky(mi, tmp_path):
    """A sky and ground (render/hemisphere.py): the renderer and the phong_integrator plugin on the saved
    XML agree; with both zero the image is the point lights' alone, bit for bit."""
    from mitsuba_p3.scene import save_scene

    base = load_scene(SCENES / "room.xml", {"shape": "sphere", "specular": "0.8"}).replace(shadows=True)
    scene = base.replace(sky=np.array([0.3, 0.35, 0.4]), ground=np.array([0.2, 0.15, 0.1]))
    save_scene(scene, tmp_path / "hemi.xml")
    loaded = load_scene(tmp_path / "hemi.xml")
    np.testing.assert_allclose(loaded.sky, scene.sky) and np.testing.assert_allclose(loaded.ground, scene.ground)
    fast = make_renderer(scene, height=120, width=160).render()
    plain = make_renderer(base, height=120, width=160).render()
    assert np.abs(fast - plain).max() > 0.05
    zero = make_renderer(scene, height=120, width=160).render({"sky": np.zeros(3, np.float32),
                                                                 "ground": np.zeros(3, np.float32)})
    assert np.array_equal(zero, plain)
    diff = np.abs(fast - _mitsubas_own_render(mi, tmp_path / "hemi.xml")).max(axis=2)
    assert (diff > 2 / 255).mean() <= 0.005, f"{(diff > 2 / 255).mean():.4%} of pixels differ"


def test_hemisphere_terms():
    """H_d is the sky for an upward normal and the ground for a downward one; H_s tends to the sky (ground)
    for a mirror direction far above (below) the horizon, scaled by the lobe's solid angle."""
    from scipy.special import erf

    from mitsuba_p3.render.hemisphere import diffuse_term, specular_term

    sky, ground = 0.8, 0.2
    assert diffuse_term(1.0, sky, ground) == pytest.approx(sky) and diffuse_term(-1.0, sky, ground) == pytest.approx(ground)
    assert diffuse_term(0.0, sky, ground) == pytest.approx(0.5)
    spec = lambda z, a: specular_term(z, a, sky, ground, np.arcsin, erf, np.sqrt, np.clip)  # noqa: E731
    assert spec(1.0, 100.0) == pytest.approx(2 * np.pi / 102 * sky, rel=1e-6)
    assert spec(-1.0, 100.0) == pytest.approx(2 * np.pi / 102 * ground, rel=1e-6)
    assert spec(0.0, 10.0) == pytest.approx(2 * np.pi / 12 * 0.5)


def test_the_ggx_lobe_is_mitsubas_roughconductor(mi):
    """render/lobes.py's GGX term equals Mitsuba's own roughconductor (GGX, Smith, a perfect mirror's
    Fresnel) evaluated at a light, times the cosine, on random pairs of directions."""
    import drjit as dr

    from mitsuba_p3.render.lobes import ggx_roughness_squared, ggx_term

    rng = np.random.default_rng(0)

    def directions(n):
        v = rng.normal(size=(n, 3))
        v[:, 2] = np.abs(v[:, 2]) + 0.01
        return v / np.linalg.norm(v, axis=1, keepdims=True)

    wi, wo = directions(300), directions(300)
    half = (wi + wo) / np.linalg.norm(wi + wo, axis=1, keepdims=True)
    for shininess in (1.0, 8.0, 64.0):
        bsdf = mi.load_dict({"type": "roughconductor", "material": "none", "distribution": "ggx",
                             "alpha": float(np.sqrt(ggx_roughness_squared(shininess)))})
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.wi, si.sh_frame = mi.Vector3f(wi.T), mi.Frame3f(mi.Vector3f(0, 0, 1))
        reference = np.asarray(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(wo.T)))[0]
        ours = ggx_term(shininess, wo[:, 2], wi[:, 2], half[:, 2], np.sqrt)
        np.testing.assert_allclose(ours, reference, rtol=1e-4, atol=1e-6)
        assert reference.max() > 0.1


@pytest.mark.parametrize("kind", ["mitsuba", "jax"])
@pytest.mark.parametrize("lobe", ["phong", "ggx"])
def test_every_lobe_renders_every_shininess_the_prior_can_draw(kind, lobe):
    """The priors' mixtures reach negative shininess: there every lobe reads alpha as 0 (Phong's flat
    lobe, GGX's roughest), finite in the image and in the material bases (Phong's overflowed to inf, and
    times a zero specular weight to NaN; an SMC run under GGX lost its cube hypothesis to NaN renders).
    One batch holds a shiny (specular 0.8) and a matte (0.0) object at each shininess."""
    scene = load_scene(SCENES / "room.xml", {"shape": "cube"}).replace(lobe=lobe)
    renderer = make_renderer(scene, kind, height=60, width=80)
    alphas = np.tile(np.array([-30.0, -3.0, -1.0, 0.0, 2.0, 500.0], np.float32), 2)
    specular = np.repeat(np.array([0.8, 0.0], np.float32), 6)
    batch = {"shininess": alphas, "specular": specular, "shift": np.zeros((12, 2), np.float32)}
    images, bases = renderer.render(batch), renderer.render_bases(batch)
    assert np.all(np.isfinite(images)) and np.all(np.isfinite(bases))
    np.testing.assert_array_equal(images[0], images[3])
    np.testing.assert_array_equal(images[6], images[9])
    assert np.abs(images[3] - images[4]).max() > 0.01


def test_the_ggx_lobe_matches_mitsubas_own_integrator_and_survives_the_xml(mi, tmp_path):
    """A scene with the GGX lobe: saved and loaded it keeps it; the renderer and the phong BSDF
    (lobe=ggx) under the phong_integrator on the saved XML agree; and it is not the Phong image."""
    from mitsuba_p3.scene import save_scene

    scene = load_scene(SCENES / "room.xml", {"shape": "sphere", "specular": "0.4", "shininess": "20",
                                             "scale": "0.05"}).replace(shadows=True, lobe="ggx")
    save_scene(scene, tmp_path / "ggx.xml")
    assert load_scene(tmp_path / "ggx.xml").lobe == "ggx"
    fast = make_renderer(scene, height=120, width=160).render()
    phong = make_renderer(scene.replace(lobe="phong"), height=120, width=160).render()
    assert np.abs(fast - phong).max() > 0.05
    diff = np.abs(fast - _mitsubas_own_render(mi, tmp_path / "ggx.xml")).max(axis=2)
    assert (diff > 2 / 255).mean() <= 0.005, f"{(diff > 2 / 255).mean():.4%} of pixels differ"
    with pytest.raises(SceneError, match="lobe"):
        scene.replace(lobe="blinn").validate()
    with pytest.raises(SceneError, match="Phong lobe"):
        scene.replace(sky=np.full(3, 0.1)).validate()
