"""Run inference on one image and keep the posterior as ArviZ InferenceData.

:func:`sample_posterior` ties the pieces together: observed image -> :class:`PosteriorModel`
-> :func:`mcmc.sample` -> :class:`Posterior` (InferenceData with the constrained
values, the unconstrained draws, log-likelihoods and sampler statistics).
Point estimates are posterior medians, the class is the most frequent one and
the yaw is the circular mode.
"""
from __future__ import annotations

import functools
import json
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import InferenceError
from ..fit.model import FittedModel
from ..space import coordinate_names
from ..shapes import SHAPES
from .likelihood import NOISES, LikelihoodConfig
from .mcmc import SamplerConfig, SamplerRun, sample
from .smc import SMCConfig, SMCRun, sample_smc
from .model import PosteriorModel

SUMMARY_VARIABLES = ("shift", "theta", "scale", "colour", "ambient", "diffuse", "specular", "shininess")



def circular_mode(angles: np.ndarray, concentration: float = 50.0, grid: int = 720) -> float:
    """The mode of a von Mises kernel density of ``angles`` (radians)."""
    angles = np.asarray(angles, np.float64).ravel()
    if angles.size > 20000:
        angles = angles[np.linspace(0, angles.size - 1, 20000).astype(int)]
    theta = np.linspace(-np.pi, np.pi, grid, endpoint=False)
    density = np.exp(concentration * np.cos(theta[:, None] - angles[None, :])).sum(axis=1)
    return float(theta[np.argmax(density)])


@dataclass
class Posterior:
    """A posterior over one image's scene, stored as ArviZ InferenceData."""

    idata: object  # arviz.InferenceData
    particles: object = None  # an SMC run's final particles (not saved): an NP3 run may start from P3's

    @property
    def shape_probabilities(self) -> dict[str, float]:
        """The posterior probability of each shape class: the share of draws of that class."""
        kappa = self.draws("kappa").astype(int)
        return dict(zip(SHAPES, (np.bincount(kappa, minlength=len(SHAPES)) / len(kappa)).tolist()))

    def to_arviz(self):
        """The posterior as ArviZ ``InferenceData`` (posterior, log likelihood, sample stats, observed image)."""
        return self.idata

    def draws(self, name: str) -> np.ndarray:
        """All draws of a variable, chains merged: (chains * draws, ...)."""
        values = self.idata.posterior[name].values
        return values.reshape((-1,) + values.shape[2:])

    def estimate(self) -> dict:
        """Point estimates: medians, the most frequent class, the circular mode of the yaw."""
        kappa = self.draws("kappa").astype(int)
        frequencies = np.bincount(kappa, minlength=len(SHAPES)) / len(kappa)
        out = {name: np.median(self.draws(name), axis=0).tolist()
               for name in ("shift", "scale", "colour", "ambient", "diffuse", "specular", "shininess")}
        out["theta"] = circular_mode(self.draws("theta"))
        out["kappa"] = int(np.argmax(frequencies))
        out["shape"] = SHAPES[out["kappa"]]
        out["class_frequencies"] = dict(zip(SHAPES, frequencies.tolist()))
        return out

    @property
    def sampler(self) -> str:
        """``smc`` or ``mh``: which sampler made the draws (their diagnostics differ)."""
        config = self.idata.posterior.attrs.get("sampler", "{}")
        return (json.loads(config) if isinstance(config, str) else config).get("sampler", "mh")

    def statistic(self, name: str, default=None):
        """A sampler statistic kept in the posterior's attributes (e.g. SMC's ``island_gap``)."""
        value = self.idata.posterior.attrs.get(name, default)
        try:
            return json.loads(value) if isinstance(value, str) else value
        except json.JSONDecodeError:
            return value

    def summary(self):
        """ArviZ summary (mean, sd, HDI, ESS, R-hat) of the constrained variables. R-hat is across MH
        chains; an SMC posterior is one pool of resampled draws, so its R-hat is undefined (NaN) and
        its run-to-run agreement is :meth:`statistic` ``island_gap``."""
        import arviz as az

        if self.sampler != "smc":
            return az.summary(self.idata, var_names=list(SUMMARY_VARIABLES), round_to="none")
        table = az.summary(self.idata, var_names=list(SUMMARY_VARIABLES), round_to="none", kind="stats")
        return table.assign(ess_bulk=np.nan, r_hat=np.nan)   # one pool: no chains to compare

    def save(self, path: str | Path) -> Path:
        """Write netCDF atomically."""
        from ..files import atomic_path

        with atomic_path(path) as temporary:
            self.idata.to_netcdf(str(temporary))
        return Path(path)

    @classmethod
    def load(cls, path: str | Path) -> "Posterior":
        import arviz as az

        path = Path(path)
        if not path.is_file():
            raise InferenceError(f"{path}: no such posterior file")
        return cls(az.from_netcdf(str(path)))


@functools.lru_cache(maxsize=8)
def _prior_functions(prior) -> tuple[Callable, Callable]:
    """The prior's bijection and log density, jitted once per prior (a fresh ``jax.jit`` per posterior
    traced and compiled them again for every image)."""
    import jax

    return jax.jit(prior.constrain), jax.jit(prior.log_prob)


def to_inference_data(model: PosteriorModel, run: SamplerRun | SMCRun, observed: np.ndarray,
                      attrs: dict) -> Posterior:
    """Constrained values, unconstrained draws, log-likelihoods and sampler statistics."""
    import arviz as az

    chains, draws, dimension = run.positions.shape
    flat = run.positions.reshape(-1, dimension)
    constrain, log_prob = _prior_functions(model.prior)
    x = {k: np.asarray(v) for k, v in constrain(flat).items()}
    log_prior = np.asarray(log_prob(flat))
    shape = lambda a: a.reshape((chains, draws) + a.shape[1:])  # noqa: E731
    posterior = {name: shape(value) for name, value in x.items()}
    posterior["kappa"] = shape(np.argmax(x["class_probabilities"], axis=-1))
    posterior["z"] = run.positions
    dims = {"shift": ["axis_xy"], "scale": ["axis_xyz"], "colour": ["rgb"], "class_probabilities": ["shape"],
            "z": ["unconstrained"]}
    coords = {"axis_xy": ["x", "y"], "axis_xyz": ["x", "y", "z"], "rgb": ["r", "g", "b"], "shape": list(SHAPES),
              "unconstrained": coordinate_names()}
    idata = az.from_dict(
        posterior=posterior,
        log_likelihood={"image": run.logdensity - shape(log_prior)},
        sample_stats={"lp": run.logdensity, **({"accepted": run.accepted} if isinstance(run, SamplerRun) else {})},
        observed_data={"image": observed},
        dims={**dims, "image": ["row", "column", "channel"]}, coords=coords,
    )
    # netCDF attributes hold strings and numbers: anything else (booleans included) as JSON
    idata.posterior.attrs.update({k: v if isinstance(v, (str, int, float)) and not isinstance(v, bool) else
                                  json.dumps(v) for k, v in attrs.items()})
    return Posterior(idata)


def sample_posterior(fitted: FittedModel, observed: np.ndarray, likelihood: LikelihoodConfig | None = None,
                sampler: SamplerConfig | SMCConfig | None = None, renderer: str = "mitsuba",
                progress: Callable[[str, int, int], None] | None = None, attrs: dict | None = None,
                start=None) -> Posterior:
    """Sample the posterior over one observed image's scene: multi-chain MH (a :class:`SamplerConfig`)
    or tempered SMC over the shape x material hypotheses (an :class:`SMCConfig`). ``start``: P3's
    final particles of this image (``Posterior.particles`` of its P3 run), from which an NP3 SMC
    run tempers the neural term in (:mod:`mitsuba_p3.infer.bridge`)."""
    import time

    likelihood = likelihood or default_likelihood(fitted, "np3")
    sampler = sampler or SamplerConfig()
    model = PosteriorModel(fitted, observed, likelihood, renderer)
    begin = time.perf_counter()
    if isinstance(sampler, SMCConfig):
        if start is None and sampler.bridge and likelihood.kind == "np3":
            # NP3 = P3 x the neural term: P3's run first, then the bridge tempers the neural term in
            colour = PosteriorModel(fitted, observed, replace(likelihood, kind="p3"), renderer)
            start = sample_smc(colour.core, colour.observation, sampler, progress).particles
        run = sample_smc(model.core, model.observation, sampler, progress, start)
    else:
        if start is not None:
            raise InferenceError("only an SMC run can start from another run's particles")
        run = sample(model.core.target(sampler.material_gibbs), sampler, progress, observation=model.observation)
    seconds = time.perf_counter() - begin
    # MH: its tuning rounds and the kept draws' acceptance; SMC: its statistics carry its steps
    mh = {"tuning": run.tuning, "acceptance": float(run.accepted.mean())} if isinstance(run, SamplerRun) else \
        {"acceptance": run.statistics.get("walk_acceptance", np.nan)}
    info = {"model": str(fitted.root), "likelihood": likelihood.kind, "sigma": likelihood.sigma,
            "noise": asdict(likelihood), "renderer": renderer, "sampler": run.config, **mh, **run.statistics,
            "seconds": seconds, **(attrs or {})}      # all of this call's (an NP3 run's includes P3's)
    posterior = to_inference_data(model, run, observed, info)
    posterior.particles = run.particles if isinstance(run, SMCRun) else None
    return posterior


def default_likelihood(fitted: FittedModel, kind: str = "np3", sigma: float | None = None,
                       noise: str = "paper") -> LikelihoodConfig:
    """The likelihood of ``kind`` (p3 or np3) under a noise model (:data:`NOISES`):

    - ``paper``: sigma 1, no outliers, power 1, no shadows (an explicit ``sigma`` selects this form
      with that sigma; the paper used 0.35 on its dark set);
    - ``fitted``: the fit's ``noise`` stage, in its Gaussian form: sigma the train residuals' RMS,
      their correlation's power beta, renders with hard shadows as in that fit;
    - ``sandwich``: the same Gaussian at the power the composite likelihood's sandwich adjustment
      gives along the object's pose and size (the outline's evidence divided by a correlation length,
      not an area);
    - ``robust``: the same stage's inlier/outlier mixture (sigma, outlier weights, beta, shadows);
    - ``spectral``: the same stage's correlated Gaussian field (the residual windows' power spectrum and
      the power of what correlation whitening leaves), renders with hard shadows;
    - ``fields``: the same stage's shading fields on the hypothesis's object, its shadow and the rest of the
      floor, marginalised (:mod:`mitsuba_p3.fit.fields`: the fields' scales and channel loading as fitted,
      the power of the correlation they leave tempering the white part alone: sigma / sqrt(power), power 1),
      hard shadows;
    - ``scaled``: the fields' form with the image's own noise scale integrated out under the prior the fit
      learnt from the train windows (:mod:`mitsuba_p3.fit.fields`, "An image's own scale").
    """
    from ..errors import ConfigError

    if noise not in NOISES:
        raise ConfigError(f"unknown noise model {noise!r}; choose {' or '.join(NOISES)}")
    if sigma is not None or noise == "paper":
        return LikelihoodConfig(kind=kind, sigma=1.0 if sigma is None else sigma)
    model = fitted.noise
    if noise == "robust":
        return LikelihoodConfig(kind=kind, sigma=model.sigma, outlier=model.outlier,
                                object_outlier=model.object_outlier, power=model.power, shadows=model.shadows)
    if noise == "sandwich":
        if model.pose_power is None or model.gaussian_sigma is None:
            raise ConfigError(f"{fitted.root} has no sandwich power; refit its noise stage: "
                              f"mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
        return LikelihoodConfig(kind=kind, sigma=model.gaussian_sigma, power=model.pose_power, shadows=model.shadows)
    if noise == "spectral":
        if model.spectral_power is None:
            raise ConfigError(f"{fitted.root} has no spectral noise form; refit its noise stage: "
                              f"mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
        return LikelihoodConfig(kind=kind, sigma=model.gaussian_sigma, power=model.spectral_power,
                                shadows=model.shadows, spectral=True)
    if noise in ("fields", "scaled"):
        if model.fields is None:
            raise ConfigError(f"{fitted.root} has no shading fields' form; refit its noise stage: "
                              f"mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
        from ..fit.fields import FieldsNoise

        fields = FieldsNoise.from_dict(model.fields)
        if noise == "scaled" and fields.scale is None:
            raise ConfigError(f"{fitted.root}'s shading fields have no prior for an image's noise scale; refit its "
                              f"noise stage: mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
        scale = (*fields.scale, fields.power) if noise == "scaled" else None
        # the power tempers the pixels given the fields, not the fields' prior: the white part's variance
        # sigma^2 / power, the taus as fitted (mitsuba_p3.fit.fields, "The power")
        return LikelihoodConfig(kind=kind, sigma=fields.white_sigma, power=1.0, shadows=model.shadows,
                                fields=fields.taus, fields_degree=fields.degree, fields_channels=fields.channels,
                                scale=scale)
    if model.gaussian_sigma is None:
        raise ConfigError(f"{fitted.root}/noise.json predates the Gaussian noise form; refit it with "
                          f"mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
    return LikelihoodConfig(kind=kind, sigma=model.gaussian_sigma, power=model.power, shadows=model.shadows)
