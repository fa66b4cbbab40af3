"""The Python API: a fitted model, an image, its posterior; the command line's defaults.

    >>> import mitsuba_p3 as p3
    >>> model = p3.load_model("out/model-small")                       # doctest: +SKIP
    >>> post = p3.infer_image(model, "out/fsclvr-small/test/large-red-metal-cube/0.png")   # doctest: +SKIP
    >>> post.shape_probabilities                                       # doctest: +SKIP
    {'cube': 0.97, 'sphere': 0.0, 'cylinder': 0.03}

:func:`infer_image` runs what ``mitsuba-p3 infer`` runs with no options: the same likelihood,
noise model, sampler and particles, built by the same function (:func:`sampler_config`), so that
the shell and Python give one answer.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from .infer.likelihood import DEFAULT_NOISE, LIKELIHOODS, NOISES
from .infer.mcmc import SamplerConfig
from .infer.smc_config import SMCConfig

# what ``mitsuba-p3 infer`` samples unless told otherwise
DEFAULT_LIKELIHOOD = "np3"
DEFAULT_SAMPLER = "auto"
DEFAULT_RENDERER = "mitsuba"
SAMPLERS = ("auto", "smc", "mh")


def load_model(path: str | Path):
    """The fitted model in folder ``path`` (written by ``mitsuba-p3 fit`` or :func:`fit`)."""
    from .fit.model import FittedModel

    return FittedModel(Path(path))


def load_image(image, resolution: tuple[int, int] | None = None) -> np.ndarray:
    """An observation as float32 (H, W, 3) in [0, 1] at the inference resolution: a PNG/JPEG/``.npy``
    path, or an array (H, W[, 3|4]) of numbers in [0, 1], checked as the command line checks a file."""
    from .images import INFERENCE_RESOLUTION, load_observation, observation_array

    resolution = resolution or INFERENCE_RESOLUTION
    if isinstance(image, (str, Path)):
        return load_observation(image, resolution)
    return observation_array(image, "the image array", resolution)


def sampler_config(sampler: str = DEFAULT_SAMPLER, noise: str = DEFAULT_NOISE, sigma: float | None = None,
                   particles: int | None = None, seed: int = 0, bridge: bool = SMCConfig.bridge,
                   renderer: str = DEFAULT_RENDERER, mh: SamplerConfig | None = None) -> SamplerConfig | SMCConfig:
    """The sampler that ``sampler`` names: ``auto`` is tempered SMC under a fitted noise model and MH under
    the paper's (``noise="paper"`` or a ``sigma``), the sampler each was measured with; SMC's particles
    default to what the renderer is measured best with where this runs."""
    from .errors import ConfigError
    from .infer.smc import default_particles

    mh = mh or SamplerConfig(seed=seed)
    if sampler not in SAMPLERS:
        raise ConfigError(f"unknown sampler {sampler!r}; choose auto, smc or mh")
    if sampler == "auto":
        sampler = "mh" if noise == "paper" or sigma is not None else "smc"
    if sampler == "mh":
        return mh
    return SMCConfig(particles=default_particles(renderer) if particles is None else particles, seed=mh.seed,
                     bridge=bridge)


def infer_image(model, image, *, likelihood: str = DEFAULT_LIKELIHOOD, noise: str = DEFAULT_NOISE,
                sampler: str = DEFAULT_SAMPLER, particles: int | None = None, seed: int = 0,
                renderer: str = DEFAULT_RENDERER, progress: Callable[[str, int, int], None] | None = None):
    """The posterior over the object in ``image`` (a path or an array, :func:`load_image`) under ``model``
    (a folder or :func:`load_model`'s result): pose, size, shape class and material, as a
    :class:`~mitsuba_p3.infer.posterior.Posterior` (``shape_probabilities``, ``estimate()``,
    ``to_arviz()``, ``save(path)``). Every default is ``mitsuba-p3 infer``'s."""
    from .errors import ConfigError
    from .infer.posterior import default_likelihood, sample_posterior

    if likelihood not in LIKELIHOODS:
        raise ConfigError(f"unknown likelihood {likelihood!r}; choose {', '.join(LIKELIHOODS)}")
    if noise not in NOISES:
        raise ConfigError(f"unknown noise model {noise!r}; choose {', '.join(NOISES)}")
    fitted = load_model(model) if isinstance(model, (str, Path)) else model
    observed = load_image(image)
    config = sampler_config(sampler, noise, None, particles, seed, renderer=renderer)
    return sample_posterior(fitted, observed, default_likelihood(fitted, likelihood, None, noise), config,
                            renderer=renderer, progress=progress,
                            attrs={"image": str(image) if isinstance(image, (str, Path)) else "array"})
