"""The Phong misfit: what the best Phong render at a pose leaves of the object (mitsuba_p3.infer.misfit)."""
from __future__ import annotations

import numpy as np
import pytest

H, W = 60, 80
POSE = {"shift": np.array([0.0, 0.0]), "theta": 0.3, "scale": np.array([0.035, 0.035, 0.035]), "kappa": 0}
MATERIAL = {"colour": np.array([0.7, 0.3, 0.2], np.float32), "ambient": np.float32(0.2),
            "diffuse": np.float32(0.6), "specular": np.float32(0.4), "shininess": np.float32(16.0)}


@pytest.fixture
def renderer(scene):
    from mitsuba_p3.render import make_renderer

    return make_renderer(scene, "mitsuba", height=H, width=W, shadows=True)


def _render(renderer, pose):
    params = {k: np.asarray(v, np.float32) for k, v in pose.items() if k != "kappa"}
    return renderer.render({**params, "kappa": np.int32(pose["kappa"]), **MATERIAL})


def test_a_phong_object_is_explained_to_its_noise(renderer):
    """A Phong render plus Gaussian noise of sd 0.01: the misfit in units of that sd is about 1."""
    from mitsuba_p3.infer.misfit import phong_misfit

    image = _render(renderer, POSE) + np.random.default_rng(0).normal(0.0, 0.01, (H, W, 3))
    assert 0.85 < phong_misfit(renderer, image, POSE, 0.01) < 1.15


def test_what_phong_cannot_render_is_measured(renderer):
    """The same object whose lower half mirrors a bright floor and upper half a dark sky (a metal's
    look, which no Phong material makes) is explained far worse; at a pose off the object, the
    misfit counts the object's pixels there (the rule learns that from train posteriors too)."""
    from mitsuba_p3.infer.misfit import phong_misfit

    image = _render(renderer, POSE)
    on_object = np.asarray(renderer.render_bases({"shift": POSE["shift"].astype(np.float32), "theta": np.float32(0.3),
                                                  "scale": POSE["scale"].astype(np.float32), "kappa": np.int32(0)})
                           )[..., :2, :].sum(axis=(-1, -2)) > 1e-6
    rows = np.nonzero(on_object)[0]
    middle = (rows.min() + rows.max()) / 2
    mirrored = image.copy()
    lower = on_object & (np.arange(H)[:, None] > middle)
    mirrored[on_object & ~lower] = 0.05
    mirrored[lower] = 0.6
    assert phong_misfit(renderer, mirrored, POSE, 0.01) > 5 * phong_misfit(renderer, image + 0.0, POSE, 0.01) + 5
    away = {**POSE, "shift": np.array([0.05, 0.05])}
    assert phong_misfit(renderer, image, away, 0.01) > 5


def test_misfit_refuses_bad_input_and_an_object_out_of_view(renderer):
    from mitsuba_p3.infer.misfit import phong_misfit

    image = _render(renderer, POSE)
    with pytest.raises(ValueError, match="renderer renders"):
        phong_misfit(renderer, image[:30], POSE, 0.01)
    with pytest.raises(ValueError, match="noise_rms"):
        phong_misfit(renderer, image, POSE, 0.0)
    assert phong_misfit(renderer, image, {**POSE, "shift": np.array([5.0, 5.0])}, 0.01) == 1.0


def test_material_rule_with_misfit_tells_kinds_whose_look_agrees():
    """Train posteriors alike in weights and colour, metals with a large Phong misfit: only the rule
    with the misfit tells them apart; a rule that needs misfits and gets none says so."""
    from mitsuba_p3.fit.attributes import AttributeRules

    rng = np.random.default_rng(1)

    def posterior(n=40):
        jitter = lambda v: np.abs(v + 0.02 * rng.standard_normal((n, 1)))  # noqa: E731
        return {"class": np.zeros(n, int), "scale": np.full((n, 3), 0.03), "colour": np.tile((0.5, 0.5, 0.5), (n, 1)),
                "ambient": jitter(0.4), "diffuse": jitter(0.5), "specular": jitter(0.2),
                "shininess": np.full((n, 1), 5.0)}

    rules = AttributeRules.from_materials({"gray-rubber": {"colour": [0.5, 0.5, 0.5], "ambient": 0.4, "diffuse": 0.5,
                                                           "specular": 0.2, "shininess": 5.0}})
    samples = [posterior() for _ in range(12)]
    kinds = ["metal"] * 6 + ["rubber"] * 6
    misfits = list(rng.uniform(3.0, 6.0, 6)) + list(rng.uniform(1.2, 2.2, 6))
    queries = [(posterior(), m, "metal") for m in (3.5, 4.0, 5.0)] + [(posterior(), m, "rubber") for m in (1.4, 1.8, 2.0)]
    with_misfit = rules.with_material_from_posteriors(samples, kinds, "weights+saturation+misfit", misfits)
    assert all(with_misfit.decide(q, m)["material"] == kind for q, m, kind in queries)
    without = rules.with_material_from_posteriors(samples, kinds, "weights+saturation")
    assert sum(without.decide(q)["material"] == kind for q, _, kind in queries) <= 5
    with pytest.raises(ValueError, match="Phong misfit"):
        with_misfit.decide(queries[0][0])
    with pytest.raises(ValueError, match="Phong misfit"):
        rules.with_material_from_posteriors(samples, kinds, "weights+saturation+misfit")
