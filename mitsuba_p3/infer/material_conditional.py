"""The material's conditionals: a mixture of trivariate Gaussians, in closed form.

Given the pose, the class and the shininess, the image is affine in the colour given the material's weights
(k_a, k_d, k_s), and affine in the weights given the colour (:mod:`mitsuba_p3.infer.material_moves`). Under a
Gaussian likelihood, exp(-x'Lambda x / 2 + eta'x), and a prior that is a mixture of diagonal
Gaussians (the material's GMM priors, :mod:`mitsuba_p3.fit.priors`), the conditional of either is
again a mixture: each prior component's posterior Gaussian, weighted by that component's evidence.
:class:`MixtureConditional` holds it in Cholesky form (3 x 3, no LAPACK call:
:mod:`mitsuba_p3.small_linalg`), draws from it and evaluates its density, which the moves use as an
independence proposal with its Hastings term.
"""
from __future__ import annotations

from typing import NamedTuple

from .. import small_linalg


class MixtureConditional(NamedTuple):
    """A material conditional that is a mixture of trivariate Gaussians (component log weights (C,), means
    (C, 3), precisions and their Cholesky factors (C, 3, 3), log determinants (C,)), in natural units: the
    weights' (k_a, k_d, k_s) given the colour, the pose, the class and the shininess; the colour's given
    the weights where the noise couples the channels."""
    log_mix: object
    mean: object
    precision: object
    chol: object
    log_det_p: object

    @classmethod
    def of(cls, log_w, mu, var, lam, eta) -> "MixtureConditional":
        """The conditional of x under a prior mixture of diagonal Gaussians (log weights (C,), means and
        variances (C, 3)) times a Gaussian likelihood exp(-x'lam x / 2 + eta'x) (lam (3, 3), eta (3,)):
        each component's posterior, and its weight by the component's evidence."""
        import jax
        import jax.numpy as jnp

        precision = jax.vmap(jnp.diag)(1.0 / var) + lam                             # (C, 3, 3)
        h = mu / var + eta
        chol = small_linalg.cholesky(precision, jnp)         # no LAPACK call (small_linalg)
        mean = small_linalg.solve(chol, h, jnp)
        log_det_p = small_linalg.log_det(chol, jnp)
        log_evidence = (-0.5 * jnp.sum(jnp.log(var), axis=1) - 0.5 * log_det_p + 0.5 * jnp.sum(h * mean, axis=1)
                        - 0.5 * jnp.sum(mu * mu / var, axis=1))
        return cls(jax.nn.log_softmax(log_w + log_evidence), mean, precision, chol, log_det_p)

    def log_q(self, w):
        import jax
        import jax.numpy as jnp

        d = w - self.mean                                                           # (C, 3)
        quad = jnp.einsum("ci,cij,cj->c", d, self.precision, d)
        return jax.scipy.special.logsumexp(self.log_mix + 0.5 * self.log_det_p - 1.5 * jnp.log(2 * jnp.pi)
                                           - 0.5 * quad)

    def draw(self, key):
        import jax
        import jax.numpy as jnp

        k_combo, k_noise = jax.random.split(key)
        combo = jax.random.categorical(k_combo, self.log_mix)
        noise = jax.random.normal(k_noise, (3,))
        return self.mean[combo] + small_linalg.backward(self.chol[combo], noise, jnp)
