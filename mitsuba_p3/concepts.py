"""Probabilistic prototypical programs: concepts as densities over object properties.

A :class:`ProtoProgram` holds one Gaussian KDE (Scott's bandwidth) per property
of the object -- its size (scale, 3-D), colour (3-D), k_a, k_d, k_s and
shininess (1-D each) -- and a categorical distribution over the shape class,
all estimated from posterior samples; the pose is dropped, since a concept does
not depend on where the object stands. A class's program is the merge of its K
shots' programs (a KDE of the concatenated samples).

The distance of an image's program C_I from a class program C_k is

    d(C_k, C_I) = sum over properties v of KL(C_k,v || C_I,v),

and p(c = k | I) = softmax_k(-d(C_k, C_I)). Each continuous KL is estimated by
Monte Carlo from ``samples`` draws of C_k,v (seeded):

    KL(P || Q) ~ (1/n) sum_i [log p(x_i) - log q(x_i)],   x_i ~ P,

an unbiased estimator whose variance falls as 1/n (``tests/test_concepts.py``
measures it). The class term is the exact KL of the categorical distributions,
whose frequencies are smoothed by ``class_smoothing`` so that a class absent
from one posterior does not make the distance infinite.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from scipy.special import log_softmax
from scipy.stats import gaussian_kde

from .errors import MitsubaP3Error
from .shapes import SHAPES

CONTINUOUS = ("scale", "colour", "ambient", "diffuse", "specular", "shininess")
PROPERTIES = CONTINUOUS + ("class",)


@dataclass(frozen=True)
class DistanceConfig:
    samples: int = 500           # Monte Carlo draws of C_k per KL term
    seed: int = 0
    class_smoothing: float = 0.01  # pseudo-count added to each class frequency
    max_points: int = 2000       # posterior samples kept per KDE (evenly thinned): bounds the cost


@dataclass
class ProtoProgram:
    """Per-property sample sets of a concept; the KDEs are built on first use."""

    samples: dict                         # property -> (n, d) array; "class" -> (n,) integer classes
    max_points: int = DistanceConfig.max_points
    _kdes: dict = field(default_factory=dict, repr=False)

    @classmethod
    def from_posterior(cls, posterior, max_points: int = DistanceConfig.max_points) -> "ProtoProgram":
        """The program of one image's posterior (:class:`mitsuba_p3.infer.posterior.Posterior`)."""
        samples = {name: np.asarray(posterior.draws(name), np.float64).reshape(-1, 3 if name in ("scale", "colour")
                                                                                 else 1)
                   for name in CONTINUOUS}
        samples["class"] = np.asarray(posterior.draws("kappa")).reshape(-1).astype(int)
        return cls(samples, max_points)

    @classmethod
    def merge(cls, programs: list["ProtoProgram"]) -> "ProtoProgram":
        """The KDE of the concatenated samples (a class program from its shots)."""
        if not programs:
            raise MitsubaP3Error("cannot merge an empty list of protoprograms")
        return cls({name: np.concatenate([p.samples[name] for p in programs]) for name in PROPERTIES},
                   programs[0].max_points)

    def kde(self, name: str) -> gaussian_kde:
        """The Gaussian KDE of a continuous property (Scott's bandwidth)."""
        if name not in self._kdes:
            points = self.samples[name]
            if len(points) > self.max_points:
                points = points[np.linspace(0, len(points) - 1, self.max_points).astype(int)]
            # a property that never varied (a fixed prior) still gets a proper density
            jitter = 1e-9 * np.random.default_rng(0).normal(size=points.shape)
            self._kdes[name] = gaussian_kde((points + jitter).T, bw_method="scott")
        return self._kdes[name]

    def class_probabilities(self, smoothing: float = DistanceConfig.class_smoothing) -> np.ndarray:
        counts = np.bincount(self.samples["class"], minlength=len(SHAPES)).astype(float) + smoothing
        return counts / counts.sum()

    def log_prob(self, values: dict) -> np.ndarray:
        """log density of the joint (independent properties) at ``values``: property -> (n, d) / (n,)."""
        total = 0.0
        for name in CONTINUOUS:
            total = total + self.kde(name).logpdf(np.asarray(values[name], np.float64).reshape(-1, self.samples[
                name].shape[1]).T)
        return total + np.log(self.class_probabilities()[np.asarray(values["class"], int)])

    def sample(self, n: int, seed: int = 0) -> dict:
        """n draws of every property from the program's densities."""
        rng = np.random.default_rng(seed)
        out = {name: self.kde(name).resample(n, seed=rng).T for name in CONTINUOUS}
        out["class"] = rng.choice(len(SHAPES), size=n, p=self.class_probabilities())
        return out


def _class_side(class_program: ProtoProgram, config: DistanceConfig) -> dict:
    """The seeded draws x ~ C_k and log C_k(x) per property: shared by every image compared with C_k."""
    rng = np.random.default_rng(config.seed)
    side = {}
    for name in CONTINUOUS:
        p = class_program.kde(name)
        x = p.resample(config.samples, seed=rng)
        side[name] = (x, p.logpdf(x))
    side["class"] = class_program.class_probabilities(config.class_smoothing)
    return side


def _kl_from_side(side: dict, image_program: ProtoProgram, config: DistanceConfig) -> dict:
    terms = {name: float(np.mean(log_p - image_program.kde(name).logpdf(x)))
             for name, (x, log_p) in ((n, side[n]) for n in CONTINUOUS)}
    p, q = side["class"], image_program.class_probabilities(config.class_smoothing)
    terms["class"] = float(np.sum(p * (np.log(p) - np.log(q))))
    return terms


def kl_terms(class_program: ProtoProgram, image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> dict:
    """The per-property KL(C_k || C_I) of the module docstring."""
    return _kl_from_side(_class_side(class_program, config), image_program, config)


def distance(class_program: ProtoProgram, image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> float:
    """d(C_k, C_I) = sum over properties of KL(C_k || C_I)."""
    return float(sum(kl_terms(class_program, image_program, config).values()))


def classify(class_programs: list[ProtoProgram], image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> np.ndarray:
    """p(c = k | I) over the given classes: softmax of the negative distances."""
    return classify_many(class_programs, [image_program], config)[0]


def classify_many(class_programs: list[ProtoProgram], image_programs: list[ProtoProgram],
                  config: DistanceConfig = DistanceConfig()) -> np.ndarray:
    """(images, classes) probabilities; each class's draws and densities are computed once."""
    sides = [_class_side(c, config) for c in class_programs]
    distances = np.array([[sum(_kl_from_side(side, image, config).values()) for side in sides]
                          for image in image_programs])
    return np.exp(log_softmax(-distances, axis=1))
