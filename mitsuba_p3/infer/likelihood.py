"""Image likelihoods: the colour likelihood (P3) and the neural likelihood (NP3's extra term).

Colour: every pixel and channel's residual r = I - render is scored by a normal
truncated to [-1, 1] (residuals of [0, 1] images cannot leave it):

    log p = sum log TruncNormal(r; 0, sigma, [-1, 1]),   sigma = 1.0 (0.35 for dark)

Neural: -weight * sum over the selected VGG16 channels m of the pixel-mean of
(F_m(I) - F_m(render))^2, weight 0.05. Both are ``jax.numpy`` functions of a
batch of renders (B, H, W, 3), so they run inside the jitted sampler.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..fit.features import Channel, neural_distance, selected_features

LIKELIHOODS = ("p3", "np3")


@dataclass(frozen=True)
class LikelihoodConfig:
    """Which likelihood and its numbers (paper defaults)."""

    kind: str = "np3"             # p3: colour only; np3: colour + neural
    sigma: float = 1.0            # 0.35 for the dark benchmark
    neural_weight: float = 0.05

    def __post_init__(self):
        from ..errors import ConfigError

        if self.kind not in LIKELIHOODS:
            raise ConfigError(f"unknown likelihood {self.kind!r}; choose p3 or np3")
        if not (isinstance(self.sigma, (int, float)) and np.isfinite(self.sigma) and self.sigma > 0):
            raise ConfigError(f"the colour likelihood's sigma must be a positive number; got {self.sigma}")
        if not (np.isfinite(self.neural_weight) and self.neural_weight >= 0):
            raise ConfigError(f"the neural weight must be >= 0; got {self.neural_weight}")


def colour_log_likelihood(observed, renders, sigma: float):
    """Sum over pixels and channels of the truncated-normal log density of the residuals (B,)."""
    import jax.numpy as jnp
    from scipy.special import ndtr

    residual = jnp.asarray(observed)[None] - renders
    count = int(np.prod(np.shape(observed)))
    # sum of log N(r; 0, sigma) - log(mass in [-1, 1]), with the constants taken out of the sum
    constant = count * (np.log(sigma) + 0.5 * np.log(2 * np.pi)
                        + np.log(float(ndtr(1.0 / sigma) - ndtr(-1.0 / sigma))))
    return -0.5 / sigma ** 2 * jnp.sum(residual * residual, axis=(-3, -2, -1)) - constant


def observe(observed: np.ndarray, config: LikelihoodConfig, channels: list[Channel] | None = None) -> dict:
    """What the likelihood needs of an observed image (H, W, 3): the image, and for NP3 its
    selected VGG16 features. A pytree, so a compiled sampler takes it as an argument and
    serves every image of the same size without recompiling."""
    if config.kind == "np3" and not channels:
        from ..errors import MitsubaP3Error

        raise MitsubaP3Error("the np3 likelihood needs the fitted model's selected VGG16 channels")
    observation = {"image": np.asarray(observed, np.float32)}
    if config.kind == "np3":
        observation["features"] = [np.asarray(f) for f in selected_features(observation["image"][None], channels)]
    return observation


def score(observation: dict, renders, config: LikelihoodConfig, channels: list[Channel] | None = None):
    """(B, H, W, 3) renders -> (B,) log-likelihoods of ``observation`` (JAX)."""
    log_lik = colour_log_likelihood(observation["image"], renders, config.sigma)
    if config.kind == "np3":
        features = selected_features(renders, channels)
        log_lik = log_lik - config.neural_weight * neural_distance(observation["features"], features)
    return log_lik


class ImageLikelihood:
    """log p(I | render) for a fixed observed image, batched over renders."""

    def __init__(self, observed: np.ndarray, config: LikelihoodConfig, channels: list[Channel] | None = None):
        self.config = config
        self.channels = channels or []
        self.observation = observe(observed, config, self.channels)

    def __call__(self, renders):
        """(B, H, W, 3) renders -> (B,) log-likelihoods (JAX)."""
        return score(self.observation, renders, self.config, self.channels)
