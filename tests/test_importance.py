"""The importance-sampling evidence of a finished run (mitsuba_p3.infer.importance), on targets whose
evidence is known in closed form."""
import numpy as np
import pytest

from mitsuba_p3.infer import importance
from mitsuba_p3.infer.importance import FREE, draw, fit, importance_evidence, log_density
from mitsuba_p3.infer.symmetry import quarter_turn

D = len(FREE)


def gaussian_target(mean: np.ndarray, cov: np.ndarray, constant: float):
    """A standard normal prior over the free coordinates times an unnormalised Gaussian likelihood
    exp(constant - (z - mean)' cov^-1 (z - mean) / 2): its evidence, its posterior, and a batched score."""
    precision = np.linalg.inv(cov)
    post_cov = np.linalg.inv(np.eye(D) + precision)
    post_mean = post_cov @ precision @ mean
    both = np.eye(D) + cov
    log_z = (constant + D / 2 * np.log(2 * np.pi) + 0.5 * np.linalg.slogdet(cov)[1]
             - D / 2 * np.log(2 * np.pi) - 0.5 * np.linalg.slogdet(both)[1]
             - 0.5 * mean @ np.linalg.solve(both, mean))

    def score(z, index, observation):
        x = np.asarray(z, np.float64)[..., FREE]
        d = x - mean
        loglik = constant - 0.5 * np.einsum("...i,ij,...j->...", d, precision, d)
        logprior = -0.5 * np.sum(x * x, axis=-1) - D / 2 * np.log(2 * np.pi)
        return loglik, logprior

    return log_z, post_mean, post_cov, score


def particles_of(rng, mean, cov, rows, count):
    z = np.zeros((rows, count, 15))
    z[..., FREE] = rng.multivariate_normal(mean, cov, size=(rows, count))
    return z


def test_estimate_matches_closed_form_evidence():
    rng = np.random.default_rng(0)
    a = rng.standard_normal((D, D)) * 0.05
    cov = a @ a.T + 0.01 * np.eye(D)
    mean = 0.3 * rng.standard_normal(D)
    log_z, post_mean, post_cov, score = gaussian_target(mean, cov, 40.0)
    position = particles_of(rng, post_mean, post_cov, 2, 64)
    tempered = np.array([log_z - 5.0, log_z + 0.3])       # one run whose path put it 5 nats low
    estimate = importance_evidence(score, np.zeros(2, np.int32), position, tempered, None, rng, 4000)
    assert np.all(np.abs(estimate.importance - log_z) < 0.15), (estimate.importance, log_z)
    assert np.all(estimate.ess > 100)
    # the kept estimate is the log of the two estimates' mean
    np.testing.assert_allclose(estimate.log_evidence, np.logaddexp(tempered, estimate.importance) - np.log(2))
    assert estimate.log_evidence[0] > tempered[0] + 4.0


def test_a_run_at_a_worse_optimum_still_estimates_low():
    """A run's proposal covers only its own particles: a run that settled away from the posterior's mass
    cannot borrow the other run's, so the island gap still shows it."""
    rng = np.random.default_rng(1)
    cov = 0.0004 * np.eye(D)
    log_z, post_mean, post_cov, score = gaussian_target(np.zeros(D), cov, 0.0)
    position = particles_of(rng, post_mean, post_cov, 2, 64)
    position[1, :, FREE] += 0.2                                     # ten posterior widths off in every coordinate
    estimate = importance_evidence(score, np.zeros(2, np.int32), position, np.full(2, log_z), None, rng, 512)
    assert abs(estimate.importance[0] - log_z) < 0.3
    assert estimate.importance[1] < log_z - 50


def test_proposal_density_is_normalised_and_matches_its_draws():
    """E_q[p / q] = 1 for a normalised p: the four copies' mixture density, with the quarter turn's Jacobian
    in the logistic yaw coordinate, is the density draw() samples. p sits on the copy a quarter turn away."""
    from scipy import stats

    rng = np.random.default_rng(2)
    position = particles_of(rng, np.zeros(D), 0.04 * np.eye(D), 1, 64)
    proposal = fit(position)
    z = draw(proposal, rng, 40000)
    log_q = log_density(proposal, z)[0]
    centre = quarter_turn(np.zeros((1, 15)), np.ones(1, int))[0][0, FREE]        # yaw a quarter turn on
    log_p = stats.multivariate_normal(centre, 0.02 * np.eye(D)).logpdf(z[0][:, FREE])
    ratio = np.exp(log_p - log_q)
    assert abs(ratio.mean() - 1.0) < 4 * ratio.std() / np.sqrt(len(ratio)) + 0.01, ratio.mean()
    # the copies: a quarter of the draws in each quarter turn of yaw about the chart
    theta = -np.pi + 2 * np.pi / (1 + np.exp(-z[0, :, 2]))
    copy = np.round(theta / (np.pi / 2)).astype(int) % 4
    np.testing.assert_allclose(np.bincount(copy, minlength=4) / len(copy), 0.25, atol=0.02)


def test_collapsed_particles_still_give_a_finite_estimate():
    rng = np.random.default_rng(3)
    log_z, post_mean, post_cov, score = gaussian_target(np.zeros(D), 0.01 * np.eye(D), 0.0)
    position = np.zeros((1, 64, 15))                                    # every particle on one point
    estimate = importance_evidence(score, np.zeros(1, np.int32), position, np.array([log_z]), None, rng, 64)
    assert np.isfinite(estimate.importance[0]) and np.isfinite(estimate.log_evidence[0])
    assert estimate.log_evidence[0] >= log_z - np.log(2) - 1e-9


@pytest.mark.parametrize("dof", [3.0, importance.DOF, 30.0])
def test_t_log_density_matches_scipy(dof):
    from scipy import stats

    rng = np.random.default_rng(4)
    a = rng.standard_normal((3, 3))
    shape = a @ a.T + np.eye(3)
    x, mean = rng.standard_normal((10, 3)), rng.standard_normal(3)
    expected = stats.multivariate_t(mean, shape, df=dof).logpdf(x)
    np.testing.assert_allclose(importance._t_logpdf(x, mean, np.linalg.cholesky(shape), dof), expected, rtol=1e-10)
