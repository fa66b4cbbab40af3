"""Protoprograms: KDEs, merge, the KL distance and its Monte Carlo estimator, classification; ADI; ECE."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mitsuba_p3.concepts import CONTINUOUS, DistanceConfig, ProtoProgram, classify, distance, kl_terms
from mitsuba_p3.evaluate import expected_calibration_error, interval95


def _program(rng, shift: float = 0.0, spread: float = 1.0, n: int = 1500, shape: int = 1) -> ProtoProgram:
    samples = {name: shift + spread * rng.normal(size=(n, 3 if name in ("scale", "colour") else 1)) * 0.1
               for name in CONTINUOUS}
    samples["class"] = np.full(n, shape)
    return ProtoProgram(samples)


def test_kl_estimate_matches_gaussians_and_its_variance_falls_with_samples():
    """KL of two 1-D Gaussians N(0, 1) || N(1, 1) is 0.5; the KDEs (Scott) widen both a little.
    The estimator's spread over seeds is measured and must fall like 1 / sqrt(n)."""
    rng = np.random.default_rng(0)
    p = ProtoProgram({"x": rng.normal(0, 1, (4000, 1)), "class": np.zeros(4000, int)}, max_points=4000)
    q = ProtoProgram({"x": rng.normal(1, 1, (4000, 1)), "class": np.zeros(4000, int)}, max_points=4000)
    p.samples, q.samples = dict(p.samples), dict(q.samples)
    estimates = {}
    for n in (100, 1600):
        values = []
        for seed in range(20):
            x = p.kde("x").sample(np.random.default_rng(seed), n)
            values.append(np.mean(p.kde("x").log_prob(x) - q.kde("x").log_prob(x)))
        estimates[n] = np.array(values)
    assert estimates[1600].mean() == pytest.approx(0.5 * 1 / (1 + 4000 ** -0.4), abs=0.05)
    ratio = estimates[100].std() / estimates[1600].std()
    assert 2.0 < ratio < 8.0, ratio   # sqrt(16) = 4


def test_kde_density_matches_scipy_and_integrates_its_samples():
    """Same density as scipy.stats.gaussian_kde (Scott), in 1-D and 3-D; resampling draws from it."""
    from scipy.stats import gaussian_kde
    from mitsuba_p3.concepts import GaussianKde
    rng = np.random.default_rng(1)
    for d in (1, 3):
        points = rng.normal(size=(300, d)) @ np.triu(np.ones((d, d)))
        x = rng.normal(size=(50, d)) * 2
        np.testing.assert_allclose(GaussianKde(points).log_prob(x), gaussian_kde(points.T).logpdf(x.T), rtol=1e-5)
        draws = GaussianKde(points).sample(rng, 20000)
        np.testing.assert_allclose(draws.mean(axis=0), points.mean(axis=0), atol=0.06 * d)
    constant = GaussianKde(np.full((100, 1), 0.3))            # a property held fixed by its prior
    assert np.isfinite(constant.log_prob(np.array([[0.3]]))).all()


def test_distance_is_zero_for_itself_and_grows_with_difference():
    rng = np.random.default_rng(1)
    base = _program(rng)
    same = distance(base, base)
    near, far = distance(base, _program(rng, shift=0.02)), distance(base, _program(rng, shift=0.2))
    assert abs(same) < 1e-9 and 0 < near < far
    terms = kl_terms(base, _program(rng, shape=2))
    assert terms["class"] > 1.0 and np.isfinite(terms["class"])   # smoothing keeps it finite


def test_distance_is_reproducible_with_its_seed():
    rng = np.random.default_rng(2)
    a, b = _program(rng), _program(rng, shift=0.05)
    assert distance(a, b, DistanceConfig(seed=3)) == distance(a, b, DistanceConfig(seed=3))


def test_distance_over_a_property_subset():
    """An ablation's distance keeps only the chosen terms; unknown or empty subsets are refused."""
    rng = np.random.default_rng(4)
    a, b = _program(rng), _program(rng, shift=0.05, shape=2)
    only = kl_terms(a, b, DistanceConfig(properties=("colour", "class")))
    assert set(only) == {"colour", "class"} and only["class"] > 1.0
    with pytest.raises(Exception, match="subset"):
        DistanceConfig(properties=("pose",))
    with pytest.raises(Exception, match="subset"):
        DistanceConfig(properties=())


def test_distance_direction_swaps_the_arguments_and_covers_a_merged_class():
    """KL(C_I || C_k) is KL(C_k || C_I) with the programs swapped, term by term. A class merged from
    two distant shots is farther than a class between them from a query like one of its shots in the
    paper's direction (the class's draws near its other shot fall outside the query), and nearer in
    the other direction."""
    rng = np.random.default_rng(5)
    a, b = _program(rng), _program(rng, shift=0.05, shape=2)
    paper, reverse = DistanceConfig(direction="class||image"), DistanceConfig(direction="image||class")
    for name, value in kl_terms(a, b, reverse).items():
        assert value == pytest.approx(kl_terms(b, a, paper)[name], rel=1e-9, abs=1e-9), name
    merged, between = ProtoProgram.merge([_program(rng), _program(rng, shift=0.5)]), _program(rng, shift=0.25)
    query = _program(rng)
    assert classify([merged, between], query, paper).argmax() == 1
    assert classify([merged, between], query, reverse).argmax() == 0
    with pytest.raises(Exception, match="direction"):
        DistanceConfig(direction="both")


def test_merge_sample_log_prob_and_classify():
    rng = np.random.default_rng(3)
    shots = [_program(rng, shift=0.5, n=400) for _ in range(3)]
    merged = ProtoProgram.merge(shots)
    assert len(merged.samples["colour"]) == 1200
    draws = merged.sample(np.random.default_rng(0), 50)
    assert draws["colour"].shape == (50, 3) and set(draws["class"]) <= {0, 1, 2}
    assert np.all(np.isfinite(merged.log_prob(draws)))
    classes = [merged, ProtoProgram.merge([_program(rng, shift=-0.5, n=400)])]
    probabilities = classify(classes, _program(rng, shift=0.5, n=400))
    assert probabilities.sum() == pytest.approx(1.0) and probabilities[0] > 0.99


def test_expected_calibration_error():
    rng = np.random.default_rng(4)
    confidence = rng.uniform(0.5, 1.0, 20000)
    calibrated = rng.uniform(size=confidence.size) < confidence
    assert expected_calibration_error(confidence, calibrated)[0] < 0.02
    overconfident = rng.uniform(size=confidence.size) < confidence - 0.3
    assert expected_calibration_error(confidence, overconfident)[0] == pytest.approx(0.3, abs=0.03)
    mean, half = interval95([0.0, 1.0] * 50)
    assert mean == 0.5 and half == pytest.approx(1.96 * 0.5025 / 10, rel=0.01)


@pytest.fixture
def cube_shot():
    from types import SimpleNamespace

    from mitsuba_p3.benchmarks.protocol import ClassLabel, Pose

    pose = Pose(0.02, -0.03, 0.035, 0.3, (0.035, 0.035, 0.035))
    return SimpleNamespace(cls=ClassLabel("cube", "red", "rubber", "large"), position=np.array([0.02, -0.03, 0.035]),
                           yaw=0.3, object_to_world=pose.object_to_world(), mesh=None)


def test_adi_is_zero_at_the_truth_blind_to_symmetry_and_grows_with_error(cube_shot):
    from mitsuba_p3.pose import adi

    assert adi(cube_shot, np.array([0.02, -0.03]), 0.3) < 1e-9
    assert adi(cube_shot, np.array([0.02, -0.03]), 0.3 + np.pi / 2) < 0.002   # a cube's symmetry
    assert adi(cube_shot, np.array([0.02, -0.03]), 0.3 + np.pi / 4) > 0.003
    errors = [adi(cube_shot, np.array([0.02 + d, -0.03]), 0.3) for d in (0.01, 0.05, 0.3)]
    assert 0.003 < errors[0] < errors[1] < errors[2] and errors[2] > 0.25   # far away: about the shift


def test_distance_terms_parse_from_text():
    from mitsuba_p3.concepts import PROPERTIES, parse_properties
    from mitsuba_p3.errors import MitsubaP3Error

    assert parse_properties("all") == PROPERTIES
    assert parse_properties("colour+class") == ("colour", "class")
    for bad in ("colour+bogus", ""):
        with pytest.raises(MitsubaP3Error, match="distance terms"):
            parse_properties(bad)


def _sharp_instance(rng, centre: np.ndarray, shape: int, n: int = 300) -> ProtoProgram:
    """A sharp posterior (sd 0.001) around one instance of a concept."""
    samples = {name: centre[:3 if name in ("scale", "colour") else 1] + 0.001 * rng.normal(
        size=(n, 3 if name in ("scale", "colour") else 1)) for name in CONTINUOUS}
    samples["class"] = np.full(n, shape)
    return ProtoProgram(samples)


def test_fit_spread_recovers_the_within_class_covariance_and_the_error_rate():
    """Instances of 40 concepts scatter by sd 0.05 around their concept's centre; one image in
    ten puts its posterior on a wrong shape. The fit recovers both."""
    from mitsuba_p3.concepts import fit_spread

    rng = np.random.default_rng(0)
    programs, shapes = {}, {}
    for c in range(40):
        centre = rng.uniform(0, 1, 3)
        shapes[f"c{c}"] = c % 3
        programs[f"c{c}"] = [_sharp_instance(rng, centre + 0.05 * rng.normal(size=3),
                                             (c % 3) if i % 10 else (c + 1) % 3) for i in range(5)]
    spread = fit_spread(programs, shapes)
    for name in CONTINUOUS:
        sd = np.sqrt(np.diag(spread.covariance[name]))
        np.testing.assert_allclose(sd, 0.05, rtol=0.2)
    assert spread.class_error == pytest.approx(0.2, abs=0.02)       # i % 10 == 0 for 1 of 5 images
    assert (spread.images, spread.classes) == (200, 40)
    with pytest.raises(Exception, match="two or more images"):
        fit_spread({"a": programs["c0"][:1]}, shapes)


@pytest.mark.parametrize("direction", ["class||image", "image||class"])
def test_a_spread_makes_instances_of_one_concept_close_and_keeps_others_apart(direction):
    """Two sharp posteriors of one concept, 2 sd of its spread apart, are far apart as the paper's
    programs (the KL counts their distance in their own tiny widths) and close with the spread;
    another concept, 10 sd away, stays much farther with the spread. In either KL direction."""
    from mitsuba_p3.concepts import ConceptSpread

    rng = np.random.default_rng(1)
    spread = ConceptSpread({name: np.eye(3 if name in ("scale", "colour") else 1) * 0.05 ** 2
                            for name in CONTINUOUS}, class_error=0.1)
    support = _sharp_instance(rng, np.full(3, 0.5), 0)
    same = _sharp_instance(rng, np.full(3, 0.6), 0)
    other = _sharp_instance(rng, np.full(3, 1.0), 0)
    config = DistanceConfig(direction=direction)
    far = distance(support, same, config)
    near = distance(support.with_spread(spread), same.with_spread(spread), config)
    assert far > 1000 and near < 25, (far, near)
    assert distance(support.with_spread(spread), other.with_spread(spread), config) > 5 * near
    probabilities = spread.class_mixture(np.array([1.0, 0.0, 0.0]))
    np.testing.assert_allclose(probabilities, [0.9, 0.05, 0.05])
    with pytest.raises(Exception, match="spread_shots"):
        DistanceConfig(spread_shots=1)


def test_student_kernels_match_scipy_and_their_draws():
    """With finite degrees of freedom, the KDE is a mixture of Student-t kernels of the Gaussian's scale
    matrix (scipy's multivariate_t), and its draws have that mixture's spread."""
    from scipy.stats import multivariate_t
    from mitsuba_p3.concepts import GaussianKde

    rng = np.random.default_rng(2)
    points, spread = rng.normal(size=(6, 3)), np.diag([0.5, 1.0, 2.0])
    kde = GaussianKde(points, spread, dof=4.0)
    scale = kde.cholesky @ kde.cholesky.T
    x = rng.normal(size=(20, 3)) * 3
    expected = np.log(np.mean([multivariate_t(loc=p, shape=scale, df=4.0).pdf(x) for p in points], axis=0))
    np.testing.assert_allclose(kde.log_prob(x), expected, rtol=1e-5)
    draws = kde.sample(rng, 200000)
    # covariance of the mixture: the centres' scatter plus the t's covariance, scale * nu / (nu - 2)
    centred = points - points.mean(axis=0)
    np.testing.assert_allclose(np.cov(draws.T), centred.T @ centred / len(points) + 2.0 * scale, rtol=0.1, atol=0.1)
    with pytest.raises(Exception, match="degrees of freedom"):
        GaussianKde(points, spread, dof=0.0)


@pytest.mark.parametrize("dof", [1.5, 4.0, np.inf])
def test_fit_tail_recovers_the_degrees_of_freedom_and_scale(dof):
    """Differences drawn from a Student-t (or a Gaussian) of a known scale: the fit picks their degrees of
    freedom from the grid and a deviation's scale, half the differences'."""
    from scipy.stats import multivariate_t
    from mitsuba_p3.concepts import fit_tail

    scale = np.array([[1.0, 0.3], [0.3, 2.0]])
    rng = np.random.default_rng(3)
    x = (rng.multivariate_normal(np.zeros(2), scale, size=3000) if np.isinf(dof)
         else multivariate_t(np.zeros(2), scale, df=dof).rvs(3000, random_state=rng))
    fitted, (deviation,) = fit_tail([x])
    assert fitted == dof
    np.testing.assert_allclose(2.0 * deviation, scale, atol=0.12)
    # one degrees of freedom for two properties: heavy-tailed ones decide it over a few Gaussian ones
    shared, scales = fit_tail([x, rng.normal(size=(40, 1))])
    assert len(scales) == 2 and (shared == dof or np.isinf(dof))


def test_fit_spread_with_tails_finds_a_heavy_tailed_concept_and_keeps_it_in_json():
    """Instances that mostly lie near their concept's centre but now and then far from it (a metal's colour
    moving with what it mirrors) get heavy-tailed kernels; Gaussian scatter keeps Gaussian ones. The
    tails travel through JSON, infinite ones as null."""
    from mitsuba_p3.concepts import ConceptSpread, fit_spread

    rng = np.random.default_rng(4)
    shapes, heavy, light = {}, {}, {}
    for c in range(60):
        centre = rng.uniform(0, 1, 3)
        shapes[f"c{c}"] = 0
        offsets = 0.02 * rng.standard_t(1.0, size=(3, 3))
        heavy[f"c{c}"] = [_sharp_instance(rng, centre + o, 0) for o in offsets]
        light[f"c{c}"] = [_sharp_instance(rng, centre + 0.02 * rng.normal(size=3), 0) for _ in range(3)]
    assert all(fit_spread(heavy, shapes, tails=True).dof(name) <= 2.0 for name in ("colour", "scale"))
    gaussian = fit_spread(light, shapes, tails=True)
    assert all(gaussian.dof(name) >= 10.0 for name in ("colour", "scale")), gaussian.tails
    spread = fit_spread(heavy, shapes, tails=True)
    again = ConceptSpread.from_json(json.loads(json.dumps(spread.to_json())))
    assert again.tails == spread.tails and fit_spread(light, shapes).tails == {}
    back = ConceptSpread.from_json(json.loads(json.dumps(ConceptSpread({}, 0.0, tails={"colour": np.inf}).to_json())))
    assert np.isinf(back.dof("colour")) and np.isinf(back.dof("scale"))
