"""What an evaluation run is: its settings, checked before any work starts, and the sampler preset."""
from __future__ import annotations

from dataclasses import asdict, dataclass, field

from ..concepts import DistanceConfig
from ..errors import ConfigError, check_counts
from ..infer.likelihood import DEFAULT_NOISE, LIKELIHOODS, NOISES, LikelihoodConfig
from ..infer.mcmc import SamplerConfig
from ..infer.smc import SMCConfig
from ..render import RENDERERS

# The MH sampler settings of the evaluation tables: shorter chains than the inference defaults, chosen because
# they give the same accuracies within their intervals.
PRESET = SamplerConfig(chains=8, steps=200, burn_in=30, tune_rounds=3, tune_steps=40)


@dataclass(frozen=True)
class EvaluationConfig:
    likelihoods: tuple = ("p3", "np3")
    sigma: float | None = None   # colour-likelihood sigma in the paper's form; None: as ``noise`` says
    # the model's noise models (fitted, the default, chosen on train classes, and sandwich: its Gaussian
    # with hard shadows at two powers; robust: its inlier/outlier mixture; spectral: its correlated
    # field) or the paper's (sigma 1, no shadows): :data:`mitsuba_p3.infer.likelihood.NOISES`
    noise: str = DEFAULT_NOISE
    renderer: str = "mitsuba"
    sampler: SamplerConfig | SMCConfig = field(default_factory=SMCConfig)
    episodes: int = 100          # per N-way K-shot setting
    queries_per_class: int = 1
    episode_seed: int = 0
    keep_draws: int = 2000       # posterior draws kept per image for its protoprogram
    distance: DistanceConfig = field(default_factory=DistanceConfig)
    jobs: int = 1                # worker processes (:func:`~mitsuba_p3.evaluate.jobs.in_workers`)
    dask: str | None = None      # a Dask scheduler address: run the per-image jobs there

    def __post_init__(self):
        likelihoods = tuple(self.likelihoods)
        object.__setattr__(self, "likelihoods", likelihoods)
        unknown = [k for k in likelihoods if k not in LIKELIHOODS]
        if unknown or not likelihoods:
            raise ConfigError(f"unknown likelihood(s) {unknown or list(likelihoods)}; choose from "
                              f"{', '.join(LIKELIHOODS)}")
        if len(set(likelihoods)) != len(likelihoods):
            raise ConfigError(f"likelihoods named twice: {', '.join(likelihoods)}")
        if self.sigma is not None:
            LikelihoodConfig(sigma=self.sigma)        # the one rule for sigma
        if self.noise not in NOISES:
            raise ConfigError(f"unknown noise model {self.noise!r}; choose {' or '.join(NOISES)}")
        if self.renderer not in RENDERERS:
            raise ConfigError(f"unknown renderer {self.renderer!r}; choose {' or '.join(RENDERERS)}")
        check_counts(self, {"episodes": 1, "queries_per_class": 1, "episode_seed": 0, "keep_draws": 1, "jobs": 1})
        if self.dask is not None and not (isinstance(self.dask, str) and self.dask.strip()):
            raise ConfigError(f"--dask must be a scheduler address such as tcp://host:8786; got {self.dask!r}")

    def cache_key(self) -> dict:
        """The settings a cached posterior depends on."""
        key = {"renderer": self.renderer, "sampler": asdict(self.sampler), "keep_draws": self.keep_draws,
               "sigma": self.sigma, "noise": self.noise}
        if self.noise in ("fields", "scaled"):
            from ..fit.fields import POWER_ON

            key["fields_power_on"] = POWER_ON    # a folder of the fields' earlier form has none: refused
        if self.noise == "scaled":
            from ..infer.bridge import SCALE_FORM

            key["scale_form"] = SCALE_FORM       # a folder of the scaled noise's first form has none: refused
        return key

