"""Priors over the scene parameters and the bijectors to the 15-D unconstrained space.

Omega = {shift (2), theta (1), scale (3), kappa (3-class simplex, 2 free), colour (3),
ambient, diffuse, specular, shininess}. Each variable has a prior in its natural
(constrained) space and a bijector from an unconstrained vector z; the sampler
works on z, with the log-density of the pushed-back prior:

    log p(z) = log p_X(f(z)) + log |det df/dz|

================  ============================================  ======================================
variable          prior (paper's values: :class:`PriorConfig`)  bijector z -> x
================  ============================================  ======================================
shift (x, y)      truncated normal, mean (0, .025), sd .08,     lo + (hi - lo) sigmoid(z)
                  bounds +-.14
theta             von Mises(0, 0) = uniform on (-pi, pi)        -pi + 2 pi sigmoid(z)
scale (3)         LogNormal(mu -3.7631, sigma .38525)           exp(z)
kappa             relaxed one-hot (Gumbel-softmax), T = .5,     softmax([z1, z2, 0])
                  probabilities 1/3
colour (3), k_a,  2-component diagonal GMM per variable,        loc + scale * z, loc and scale the
k_d, k_s, alpha   fitted by EM to the optimised materials       GMM's mean and standard deviation
================  ============================================  ======================================

Densities are written in ``jax.numpy`` so the sampler can jit and differentiate
them; :meth:`Prior.sample` draws from the prior with numpy.
"""
from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from ..space import MATERIAL_VARIABLES, SLICES, hypothesis_of


@dataclass(frozen=True)
class PriorConfig:
    """Every prior number in one place; the defaults are the paper's (PAPER_NOTES.md)."""

    shift_mean: tuple = (0.0, 0.025)
    shift_sd: float = 0.08
    shift_bound: float = 0.14
    theta_concentration: float = 0.0   # von Mises; 0 = uniform on the circle
    scale_mean: float = 0.025          # of the log-normal, metres
    scale_variance: float = 1e-4       # the authors' "scale scale" is a variance
    class_probabilities: tuple = (1 / 3, 1 / 3, 1 / 3)
    class_temperature: float = 0.5
    gmm_components: int = 2
    gmm_seed: int = 0

    def __post_init__(self):
        from ..errors import ConfigError, check_counts, check_positive

        object.__setattr__(self, "shift_mean", tuple(self.shift_mean))
        object.__setattr__(self, "class_probabilities", tuple(self.class_probabilities))
        check_counts(self, {"gmm_components": 1, "gmm_seed": 0}, "prior ")
        check_positive(self, ("shift_sd", "shift_bound", "scale_mean", "scale_variance", "class_temperature"),
                       "prior ")
        if not self.theta_concentration >= 0:
            raise ConfigError(f"prior theta-concentration must be >= 0; got {self.theta_concentration}")
        p = self.class_probabilities
        if len(p) != 3 or min(p) <= 0 or abs(sum(p) - 1) > 1e-6:
            raise ConfigError(f"prior class-probabilities must be 3 positive numbers summing to 1; got {p}")

    @property
    def scale_log_sigma(self) -> float:
        return float(np.sqrt(np.log1p(self.scale_variance / self.scale_mean ** 2)))

    @property
    def scale_log_mu(self) -> float:
        return float(np.log(self.scale_mean) - 0.5 * self.scale_log_sigma ** 2)


@dataclass
class GMM:
    """A diagonal Gaussian mixture: weights (K,), means (K, D), variances (K, D)."""

    weights: np.ndarray
    means: np.ndarray
    variances: np.ndarray

    @property
    def mean(self) -> np.ndarray:
        return self.weights @ self.means

    @property
    def std(self) -> np.ndarray:
        second = self.weights @ (self.variances + self.means ** 2)
        return np.sqrt(np.maximum(second - self.mean ** 2, 1e-12))

    def log_prob(self, x):
        """log density at x (..., D), jax-traceable."""
        import jax.numpy as jnp
        from jax.scipy.special import logsumexp

        x = jnp.asarray(x)[..., None, :]
        per = -0.5 * jnp.sum((x - self.means) ** 2 / self.variances + jnp.log(2 * jnp.pi * self.variances), -1)
        return logsumexp(per + jnp.log(self.weights), axis=-1)

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        component = rng.choice(len(self.weights), size=n, p=self.weights / self.weights.sum())
        return self.means[component] + np.sqrt(self.variances[component]) * rng.standard_normal(
            (n, self.means.shape[1]))

    def as_dict(self) -> dict:
        return {"weights": self.weights.tolist(), "means": self.means.tolist(), "variances": self.variances.tolist()}

    @classmethod
    def from_dict(cls, d: dict) -> "GMM":
        return cls(*(np.asarray(d[k], np.float64) for k in ("weights", "means", "variances")))


def fit_gmm(values: np.ndarray, components: int = 2, seed: int = 0) -> GMM:
    """EM fit (scikit-learn) of a diagonal GMM to (N, D) values; fewer points -> fewer components."""
    from sklearn.mixture import GaussianMixture

    values = np.asarray(values, np.float64).reshape(len(values), -1)
    if len(values) < 2:
        from ..errors import FitError

        raise FitError(f"a GMM prior needs at least 2 fitted materials, got {len(values)}")
    k = min(components, len(values))
    model = GaussianMixture(k, covariance_type="diag", random_state=seed, reg_covar=1e-4).fit(values)
    return GMM(model.weights_, model.means_, model.covariances_)


def _log_sigmoid(z):
    import jax.numpy as jnp

    return -jnp.logaddexp(0.0, -z)


class Prior:
    """The prior over Omega with its bijectors; :meth:`log_prob` works on the unconstrained z."""

    def __init__(self, config: PriorConfig, gmms: dict[str, GMM]):
        missing = set(MATERIAL_VARIABLES) - set(gmms)
        if missing:
            raise ValueError(f"GMM priors missing for {sorted(missing)}")
        self.config = config
        self.gmms = gmms

    # ------------------------------------------------------------ bijectors
    def constrain(self, z) -> dict:
        """z (..., 15) -> constrained values (jax-traceable)."""
        import jax
        import jax.numpy as jnp

        c = self.config
        z = jnp.asarray(z)
        lo, hi = -c.shift_bound, c.shift_bound
        logits = jnp.concatenate([z[..., SLICES["kappa"]], jnp.zeros(z.shape[:-1] + (1,))], axis=-1)
        out = {
            "shift": lo + (hi - lo) * jax.nn.sigmoid(z[..., SLICES["shift"]]),
            "theta": -jnp.pi + 2 * jnp.pi * jax.nn.sigmoid(z[..., 2]),
            "scale": jnp.exp(z[..., SLICES["scale"]]),
            "class_probabilities": jax.nn.softmax(logits, axis=-1),
        }
        for name in MATERIAL_VARIABLES:
            g = self.gmms[name]
            value = g.mean + g.std * z[..., SLICES[name]]
            out[name] = value if name == "colour" else value[..., 0]
        return out

    def unconstrain(self, x: dict) -> np.ndarray:
        """Constrained values (numpy; ``class_probabilities`` on the simplex) -> z (..., 15)."""
        c = self.config
        lo, hi = -c.shift_bound, c.shift_bound
        logit = lambda p: np.log(p) - np.log1p(-p)  # noqa: E731
        probs = np.asarray(x["class_probabilities"], np.float64)
        parts = {
            "shift": logit((np.asarray(x["shift"]) - lo) / (hi - lo)),
            "theta": logit((np.asarray(x["theta"]) + np.pi) / (2 * np.pi))[..., None],
            "scale": np.log(np.asarray(x["scale"])),
            "kappa": np.log(probs[..., :2]) - np.log(probs[..., 2:3]),
        }
        for name in MATERIAL_VARIABLES:
            g = self.gmms[name]
            value = np.asarray(x[name], np.float64)
            value = value if name == "colour" else value[..., None]
            parts[name] = (value - g.mean) / g.std
        return np.concatenate([parts[k] for k in SLICES], axis=-1)

    # ------------------------------------------------------------ densities
    def log_prob_parts(self, z) -> dict:
        """Per-variable log-density of z (prior at f(z) plus log-Jacobian), jax-traceable."""
        import jax.numpy as jnp
        from jax.scipy.special import gammaln, logsumexp
        from jax.scipy.stats import norm

        c = self.config
        z = jnp.asarray(z)
        x = self.constrain(z)
        parts = {}
        # shift: truncated normal on [lo, hi]; jacobian (hi - lo) s (1 - s)
        lo, hi = -c.shift_bound, c.shift_bound
        mean, sd = jnp.asarray(c.shift_mean), c.shift_sd
        mass = norm.cdf((hi - mean) / sd) - norm.cdf((lo - mean) / sd)
        zs = z[..., SLICES["shift"]]
        log_jac = jnp.log(hi - lo) + _log_sigmoid(zs) + _log_sigmoid(-zs)
        parts["shift"] = jnp.sum(norm.logpdf(x["shift"], mean, sd) - jnp.log(mass) + log_jac, -1)
        # theta: von Mises(0, kappa) on (-pi, pi); jacobian 2 pi s (1 - s)
        kappa_vm = c.theta_concentration
        zt = z[..., 2]
        log_vm = kappa_vm * jnp.cos(x["theta"]) - jnp.log(2 * jnp.pi * _bessel_i0(kappa_vm))
        parts["theta"] = log_vm + jnp.log(2 * jnp.pi) + _log_sigmoid(zt) + _log_sigmoid(-zt)
        # scale: log-normal; with x = exp(z) the pushed-back density is normal in z
        zl = z[..., SLICES["scale"]]
        parts["scale"] = jnp.sum(norm.logpdf(zl, c.scale_log_mu, c.scale_log_sigma), -1)
        # kappa: relaxed one-hot (Concrete) density on the simplex, times softmax-centred jacobian
        p = x["class_probabilities"]
        n = p.shape[-1]
        lam = c.class_temperature
        log_pi = jnp.log(jnp.asarray(c.class_probabilities))
        log_p = jnp.log(p)
        concrete = (gammaln(n) + (n - 1) * jnp.log(lam) + jnp.sum(log_pi - (lam + 1) * log_p, -1)
                    - n * logsumexp(log_pi - lam * log_p, axis=-1))
        parts["kappa"] = concrete + jnp.sum(log_p, -1)
        # GMM variables: affine bijector, jacobian prod(std)
        for name in MATERIAL_VARIABLES:
            g = self.gmms[name]
            value = x[name] if name == "colour" else x[name][..., None]
            parts[name] = g.log_prob(value) + float(np.sum(np.log(g.std)))
        return parts

    def log_prob(self, z):
        """log p(z) of the unconstrained vector (..., 15)."""
        return sum(self.log_prob_parts(z).values())

    # ------------------------------------------------------------ sampling
    def sample_constrained(self, rng: np.random.Generator, n: int) -> dict[str, np.ndarray]:
        """n draws from the prior in the natural space (numpy)."""
        from scipy.stats import truncnorm, vonmises

        c = self.config
        mean = np.asarray(c.shift_mean)
        a, b = (-c.shift_bound - mean) / c.shift_sd, (c.shift_bound - mean) / c.shift_sd
        shift = truncnorm.rvs(a, b, loc=mean, scale=c.shift_sd, size=(n, 2), random_state=rng)
        if c.theta_concentration > 0:
            theta = vonmises.rvs(c.theta_concentration, size=n, random_state=rng)
        else:
            theta = rng.uniform(-np.pi, np.pi, size=n)
        scale = np.exp(c.scale_log_mu + c.scale_log_sigma * rng.standard_normal((n, 3)))
        gumbel = -np.log(-np.log(rng.uniform(size=(n, 3))))
        logits = (np.log(np.asarray(c.class_probabilities)) + gumbel) / c.class_temperature
        probs = np.exp(logits - logits.max(-1, keepdims=True))
        probs /= probs.sum(-1, keepdims=True)
        out = {"shift": shift, "theta": theta, "scale": scale, "class_probabilities": probs}
        for name in MATERIAL_VARIABLES:
            draws = self.gmms[name].sample(rng, n)
            out[name] = draws if name == "colour" else draws[:, 0]
        return out

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n draws of z (n, 15)."""
        return self.unconstrain(self.sample_constrained(rng, n))

    # ------------------------------------------------------------ hypotheses
    def specular_threshold(self) -> float:
        """Unconstrained specular value between its GMM's two components (inf for one component):
        below it a point is matte, above it shiny."""
        g = self.gmms["specular"]
        if len(g.weights) < 2:
            return float("inf")
        centres = (np.sort(g.means[:, 0]) - g.mean[0]) / g.std[0]
        return float(centres[:2].mean())

    def hypothesis(self, z):
        """The discrete hypothesis (shape class x material kind, :data:`mitsuba_p3.space.HYPOTHESES`)
        of positions z (..., 15), jax-traceable; numpy in, numpy out."""
        if isinstance(z, np.ndarray):
            return hypothesis_of(z, self.specular_threshold(), np)
        import jax.numpy as jnp

        return hypothesis_of(z, self.specular_threshold(), jnp)

    # ------------------------------------------------------------ storage
    def as_dict(self) -> dict:
        return {"config": asdict(self.config), "gmms": {k: g.as_dict() for k, g in self.gmms.items()},
                "layout": {k: [s.start, s.stop] for k, s in SLICES.items()}}

    @classmethod
    def from_dict(cls, d: dict) -> "Prior":
        config = PriorConfig(**{k: tuple(v) if isinstance(v, list) else v for k, v in d["config"].items()})
        return cls(config, {k: GMM.from_dict(v) for k, v in d["gmms"].items()})


def _bessel_i0(x: float) -> float:
    from scipy.special import i0

    return float(i0(x))


def fit_priors(materials: dict[str, dict], config: PriorConfig | None = None) -> Prior:
    """Fit the GMM priors to the optimised materials (one row per colour+material pair)."""
    config = config or PriorConfig()
    rows = list(materials.values())
    gmms = {}
    for name in MATERIAL_VARIABLES:
        values = np.array([np.atleast_1d(row[name]) for row in rows], np.float64)
        gmms[name] = fit_gmm(values, config.gmm_components, config.gmm_seed)
    return Prior(config, gmms)
