"""Probabilistic prototypical programs: concepts as densities over object properties.

A :class:`ProtoProgram` holds one Gaussian KDE (Scott's bandwidth) per property
of the object -- its size (scale, 3-D), colour (3-D), k_a, k_d, k_s and
shininess (1-D each) -- and a categorical distribution over the shape class,
all estimated from posterior samples; the pose is dropped, since a concept does
not depend on where the object stands. A class's program is the merge of its K
shots' programs (a KDE of the concatenated samples).

The paper's distance of an image's program C_I from a class program C_k is

    d(C_k, C_I) = sum over properties v of KL(C_k,v || C_I,v),

and p(c = k | I) = softmax_k(-d(C_k, C_I)); this project's default turns each KL
round (KL(C_I,v || C_k,v), below). Each continuous KL is estimated by Monte
Carlo from ``samples`` draws of its first argument (seeded):

    KL(P || Q) ~ (1/n) sum_i [log p(x_i) - log q(x_i)],   x_i ~ P,

an unbiased estimator whose variance falls as 1/n (``tests/test_concepts.py``
measures it). The class term is the exact KL of the categorical distributions,
whose frequencies are smoothed by ``class_smoothing`` so that a class absent
from one posterior does not make the distance infinite.

**The concept's spread.** The program of one image is its posterior: how
sure the sampler is of *this* object. A concept is broader: two images of one
class differ by more than either posterior's width (the light falls otherwise,
the sampler errs), and once the likelihood is sharp, the KL between two such
posteriors measures that difference in units of their tiny widths, so weakly
identified properties (shininess, k_a) swamp the colour. A
:class:`ConceptSpread`, fitted on *train* classes (:func:`fit_spread`), is the
remedy of a hierarchical model: each property's kernels are widened by the
pooled within-class covariance of the train posteriors' means, and the class
distribution is mixed with a uniform one at the sampler's error rate on train
shapes, so a program is the predictive density of another instance of its
concept. Without a spread the programs are the paper's.

**The concept's tails.** Two images of one class are mostly a spread apart and
now and then many: a metal's colour posterior moves with what it mirrors, a
misread image lands far off. Under Gaussian kernels such a gap costs its squared
distance, tens of nats that drown every other term. The spread's kernels are
therefore Student-t ones (a within-class scale that is itself uncertain: the
predictive density of a scale mixture of Gaussians), whose degrees of freedom
(one, shared by the properties) and scales are fitted by maximum likelihood on
the differences between two train images' posterior means of one class
(:func:`fit_tail`), so a far gap costs about its log. Fitted, not chosen by
accuracy; held-out train classes' episodes decided that fitted tails replace
Gaussian kernels.

**The KL's direction.** The paper's KL(C_k || C_I) draws from the class
program and asks the query's posterior to explain every draw. A K-shot class
program is a mixture of K posteriors, so its draws near the other shots fall
outside a sharp query's posterior even when the query is like one of them: the
more shots, the farther every class. ``direction="image||class"`` turns it
round: KL(C_I || C_k) = -E_{x~C_I}[log C_k(x)] - H(C_I), and H(C_I) is the same
for every class, so softmax_k(-KL(C_I || C_k)) weighs each class by the
expected log predictive density of the query's posterior under the concept,
which a mixture of shots makes larger, not smaller. In 1-shot episodes, with
both programs one posterior, the two directions differ little. Chosen on
held-out train classes' 1- and 5-shot episodes; ``class||image`` is the paper's.

Every density of the project speaks one vocabulary: ``log_prob(x)`` and
``sample(rng, n)`` (:class:`GaussianKde`, :class:`ProtoProgram`, and the prior's
:class:`~mitsuba_p3.fit.priors.GMM` and :class:`~mitsuba_p3.fit.priors.Prior`).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass, field

import numpy as np
from scipy.special import gammaln, log_softmax

from .errors import MitsubaP3Error, check_counts
from .shapes import SHAPES

CONTINUOUS = ("scale", "colour", "ambient", "diffuse", "specular", "shininess")
PROPERTIES = CONTINUOUS + ("class",)
DIRECTIONS = ("class||image", "image||class")


@dataclass(frozen=True)
class DistanceConfig:
    samples: int = 500           # Monte Carlo draws of C_k per KL term
    seed: int = 0
    class_smoothing: float = 0.01  # pseudo-count added to each class frequency
    max_points: int = 500        # posterior samples kept per KDE (evenly thinned): bounds the cost
    properties: tuple = PROPERTIES  # the terms of the distance (all of them in the paper; fewer for ablations)
    # train images per train class whose posteriors fit the programs' ConceptSpread (0: the paper's programs)
    spread_shots: int = 3
    # the KL's direction: "image||class" (KL(C_I || C_k); chosen on held-out train classes' 1- and 5-shot
    # episodes) or "class||image" (the paper's, KL(C_k || C_I))
    direction: str = "image||class"
    # the concept's kernels: Student-t of tails fitted on train classes (True) or Gaussian (False)
    tails: bool = True

    def __post_init__(self):
        unknown = set(self.properties) - set(PROPERTIES)
        if unknown or not self.properties:
            raise MitsubaP3Error(f"distance properties must be a non-empty subset of {PROPERTIES}; "
                                 f"got {tuple(self.properties)}")
        check_counts(self, {"spread_shots": 0})
        if self.direction not in DIRECTIONS:
            raise MitsubaP3Error(f"unknown distance direction {self.direction!r}; choose {' or '.join(DIRECTIONS)}")
        if self.spread_shots == 1:
            raise MitsubaP3Error("spread_shots must be 0 (no concept spread) or 2 or more train images per class "
                                 "(a within-class spread needs two); got 1")

    @property
    def continuous(self) -> tuple:
        """The continuous properties among the distance's terms."""
        return tuple(v for v in CONTINUOUS if v in self.properties)


def parse_properties(text: str) -> tuple:
    """Distance terms from text: ``all`` or properties joined by ``+`` (``colour+class``)."""
    properties = PROPERTIES if text.strip() == "all" else tuple(p.strip() for p in text.split("+"))
    if not properties or not set(properties) <= set(PROPERTIES):
        raise MitsubaP3Error(f"unknown distance terms {text!r}; choose 'all' or some of {'+'.join(PROPERTIES)}")
    return properties


@functools.cache
def _log_kernel_sum():
    """Jitted log sum_j exp(-|z_i - p_j|^2 / 2) for whitened queries z (m, d) and points p (n, d)."""
    import jax
    import jax.numpy as jnp

    return jax.jit(lambda z, p: jax.nn.logsumexp(-0.5 * jnp.sum((z[:, None, :] - p[None]) ** 2, axis=-1), axis=1))


@functools.cache
def _log_student_kernel_sum():
    """Jitted log sum_j (1 + |z_i - p_j|^2 / nu)^(-(nu + d) / 2), the Student-t kernels' sum."""
    import jax
    import jax.numpy as jnp

    def kernel_sum(z, p, nu):
        squared = jnp.sum((z[:, None, :] - p[None]) ** 2, axis=-1)
        return jax.nn.logsumexp(-0.5 * (nu + z.shape[1]) * jnp.log1p(squared / nu), axis=1)

    return jax.jit(kernel_sum)


def student_log_norm(nu: float, d: int) -> float:
    """log of the multivariate Student-t density's constant for a unit scale matrix."""
    return float(gammaln(0.5 * (nu + d)) - gammaln(0.5 * nu) - 0.5 * d * np.log(nu * np.pi))


class GaussianKde:
    """A Gaussian KDE with Scott's bandwidth, the density of ``scipy.stats.gaussian_kde``;
    with ``spread`` (a covariance), each kernel is widened by it (the density convolved with
    N(0, spread)). With finite ``dof``, each kernel is instead a Student-t of that many degrees
    of freedom and the same scale matrix (Scott's covariance plus the spread): a concept whose
    within-class scale is itself uncertain, which charges a far draw about its log distance.

    Its own class for speed: the density is one fused, jitted kernel sum in
    whitened coordinates, so scoring an episode takes a fraction of a second.
    """

    def __init__(self, points: np.ndarray, spread: np.ndarray | None = None, dof: float = np.inf):
        points = np.asarray(points, np.float64)
        n, d = points.shape
        self.points = points
        factor = n ** (-1.0 / (d + 4))                      # Scott's rule
        covariance = np.atleast_2d(np.cov(points, rowvar=False)) * factor ** 2
        if spread is not None:                               # a concept's spread around each draw
            covariance = covariance + np.atleast_2d(spread)
        # a property that never varied (a fixed prior) still gets a proper density
        covariance += np.eye(d) * max(1e-12, 1e-9 * np.trace(covariance) / d)
        if not dof > 0:
            raise MitsubaP3Error(f"a Student-t kernel needs positive degrees of freedom; got {dof}")
        self.dof = float(dof)
        # the kernels' scale matrix (their covariance when Gaussian)
        self.cholesky = np.linalg.cholesky(covariance)
        self._whiten = np.linalg.inv(self.cholesky)
        self._white_points = (points @ self._whiten.T).astype(np.float32)
        self._log_norm = np.log(n) + np.sum(np.log(np.diag(self.cholesky))) - (
            -0.5 * d * np.log(2 * np.pi) if np.isinf(self.dof) else student_log_norm(self.dof, d))

    def log_prob(self, x: np.ndarray) -> np.ndarray:
        """log density at the rows of ``x`` (m, d)."""
        z = (np.asarray(x, np.float64).reshape(-1, self.points.shape[1]) @ self._whiten.T).astype(np.float32)
        if np.isinf(self.dof):
            total = _log_kernel_sum()(z, self._white_points)
        else:
            total = _log_student_kernel_sum()(z, self._white_points, np.float32(self.dof))
        return np.asarray(total, np.float64) - self._log_norm

    def sample(self, rng: np.random.Generator, n: int) -> np.ndarray:
        """n draws (n, d): a random kernel centre plus its Gaussian (or Student-t) noise."""
        centres = self.points[rng.integers(len(self.points), size=n)]
        noise = rng.standard_normal((n, self.points.shape[1])) @ self.cholesky.T
        if not np.isinf(self.dof):
            noise = noise * np.sqrt(self.dof / rng.chisquare(self.dof, size=(n, 1)))
        return centres + noise


@dataclass(frozen=True)
class ConceptSpread:
    """How far apart two instances of one concept are, as the sampler sees them (fitted on train classes).

    ``covariance``: per continuous property, the pooled within-class covariance of the
    posterior means (for Student-t kernels, their fitted scale matrix); ``class_error``: the
    mean posterior probability of a wrong shape on the train images; ``tails``: per continuous
    property, the kernels' degrees of freedom (absent or infinite: Gaussian kernels).
    ``images`` and ``classes`` say what it was fitted on.
    """

    covariance: dict
    class_error: float
    images: int = 0
    classes: int = 0
    tails: dict = field(default_factory=dict)

    def dof(self, name: str) -> float:
        """The degrees of freedom of a property's kernels (infinite: Gaussian)."""
        return float(self.tails.get(name, np.inf))

    def to_json(self) -> dict:
        return {"covariance": {k: np.asarray(v).tolist() for k, v in self.covariance.items()},
                "class_error": self.class_error, "images": self.images, "classes": self.classes,
                "tails": {k: (None if np.isinf(v) else float(v)) for k, v in self.tails.items()}}

    @classmethod
    def from_json(cls, record: dict) -> "ConceptSpread":
        return cls({k: np.atleast_2d(np.asarray(v, np.float64)) for k, v in record["covariance"].items()},
                   float(record["class_error"]), int(record.get("images", 0)), int(record.get("classes", 0)),
                   {k: (np.inf if v is None else float(v)) for k, v in record.get("tails", {}).items()})

    def class_mixture(self, probabilities: np.ndarray) -> np.ndarray:
        """Mix a class distribution with the uniform one so that a certain class keeps
        probability 1 - class_error (each other class class_error / (K - 1))."""
        k = len(probabilities)
        weight = min(1.0, self.class_error * k / (k - 1))
        return (1.0 - weight) * probabilities + weight / k


# the degrees of freedom fit_tail chooses among (inf: Gaussian)
TAIL_GRID = (1.0, 1.5, 2.0, 3.0, 4.0, 6.0, 10.0, 20.0, 50.0, np.inf)


def fit_student(x: np.ndarray, dof: float, iterations: int = 200) -> tuple[np.ndarray, float]:
    """The maximum-likelihood scale matrix of a zero-mean multivariate Student-t of ``dof`` degrees of
    freedom (the Gaussian's covariance for infinite dof) for the rows of ``x`` (n, d), by the
    classical EM (each row weighted by (nu + d) / (nu + its squared Mahalanobis distance)), and the
    log likelihood it reaches."""
    n, d = x.shape
    jitter = np.eye(d) * max(1e-12, 1e-9 * np.trace(x.T @ x) / max(n, 1) / d)
    scale = x.T @ x / n + jitter
    for _ in range(0 if np.isinf(dof) else iterations):      # a Gaussian's maximum is the start itself
        squared = np.sum(np.linalg.solve(np.linalg.cholesky(scale), x.T) ** 2, axis=0)
        new = (x * ((dof + d) / (dof + squared))[:, None]).T @ x / n + jitter
        if np.allclose(new, scale, rtol=1e-8, atol=0):
            break
        scale = new
    return scale, student_log_likelihood(x, scale, dof)


def student_log_likelihood(x: np.ndarray, scale: np.ndarray, dof: float) -> float:
    """log likelihood of the rows of ``x`` (n, d) under a zero-mean multivariate Student-t of ``dof``
    degrees of freedom and scale matrix ``scale`` (a Gaussian of that covariance for infinite dof)."""
    n, d = x.shape
    cholesky = np.linalg.cholesky(scale)
    squared = np.sum(np.linalg.solve(cholesky, x.T) ** 2, axis=0)
    log_det = np.sum(np.log(np.diag(cholesky)))
    if np.isinf(dof):
        return float(np.sum(-0.5 * squared) - n * (0.5 * d * np.log(2 * np.pi) + log_det))
    return float(np.sum(-0.5 * (dof + d) * np.log1p(squared / dof)) + n * (student_log_norm(dof, d) - log_det))


def fit_tail(differences: list[np.ndarray]) -> tuple[float, list[np.ndarray]]:
    """One degrees of freedom among :data:`TAIL_GRID`, shared by every property, and each property's
    scale matrix of one image's deviation, under which the within-class differences of two images'
    posterior means (one (n, d_v) array per property) are most likely together (a difference's scale
    taken as twice a deviation's). Shared because one number is estimated far more stably than one
    per property from a few dozen pairs, and a property left Gaussian beside heavy-tailed ones would
    outweigh them all."""
    fits = {dof: [fit_student(x, dof) for x in differences] for dof in TAIL_GRID}
    dof = max(fits, key=lambda k: sum(log_likelihood for _, log_likelihood in fits[k]))
    return dof, [scale / 2.0 for scale, _ in fits[dof]]


def fit_spread(programs: dict[str, list["ProtoProgram"]], shapes: dict[str, int | None],
               tails: bool = False) -> ConceptSpread:
    """The :class:`ConceptSpread` of train classes: ``programs`` maps a class to its images' programs
    (at least two for some class), ``shapes`` a class to its true shape's index (None for a shape
    outside :data:`~mitsuba_p3.shapes.SHAPES`, which does not count towards ``class_error``).
    With ``tails``, the kernels become Student-t ones whose degrees of freedom (one for every property)
    and scales are those under which the differences between two images of one class are most likely
    (:func:`fit_tail`; the scales then stand in ``covariance``)."""
    groups = [group for group in programs.values() if group]
    images = sum(len(group) for group in groups)
    if images - len(groups) < 1:
        raise MitsubaP3Error("fitting a concept spread needs two or more images of at least one class")
    covariance, differences = {}, {}
    for name in CONTINUOUS:
        scatter, differences[name] = 0.0, []
        for group in groups:
            means = np.stack([p.samples[name].mean(axis=0) for p in group])
            centred = means - means.mean(axis=0)
            scatter = scatter + centred.T @ centred
            differences[name] += [means[i] - means[j] for i in range(len(means)) for j in range(i + 1, len(means))]
        covariance[name] = np.atleast_2d(scatter / (images - len(groups)))
    dofs = {}
    if tails:
        dof, scales = fit_tail([np.stack(differences[name]) for name in CONTINUOUS])
        covariance = dict(zip(CONTINUOUS, scales))
        dofs = {name: dof for name in CONTINUOUS}
    wrong = [1.0 - p.class_probabilities()[shapes[name]]
             for name, group in programs.items() if shapes.get(name) is not None for p in group]
    return ConceptSpread(covariance, float(np.mean(wrong)) if wrong else 0.0, images, len(groups), dofs)


@dataclass
class ProtoProgram:
    """Per-property sample sets of a concept; the KDEs are built on first use. With a
    :class:`ConceptSpread`, the kernels and class distribution are widened by it."""

    samples: dict                         # property -> (n, d) array; "class" -> (n,) integer classes
    max_points: int = DistanceConfig.max_points
    spread: ConceptSpread | None = None
    _kdes: dict = field(default_factory=dict, repr=False)

    def with_spread(self, spread: ConceptSpread | None) -> "ProtoProgram":
        """The same samples under another concept spread (None: the paper's program)."""
        return ProtoProgram(self.samples, self.max_points, spread)

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
                   programs[0].max_points, programs[0].spread)

    def kde(self, name: str) -> GaussianKde:
        """The Gaussian KDE of a continuous property (Scott's bandwidth), on at most ``max_points``."""
        if name not in self._kdes:
            points = self.samples[name]
            if len(points) > self.max_points:
                points = points[np.linspace(0, len(points) - 1, self.max_points).astype(int)]
            self._kdes[name] = (GaussianKde(points, self.spread.covariance[name], self.spread.dof(name))
                                if self.spread else GaussianKde(points))
        return self._kdes[name]

    def class_probabilities(self, smoothing: float = DistanceConfig.class_smoothing) -> np.ndarray:
        counts = np.bincount(self.samples["class"], minlength=len(SHAPES)).astype(float) + smoothing
        probabilities = counts / counts.sum()
        return self.spread.class_mixture(probabilities) if self.spread else probabilities

    def log_prob(self, values: dict) -> np.ndarray:
        """log density of the joint (independent properties) at ``values``: property -> (n, d) / (n,)."""
        total = 0.0
        for name in CONTINUOUS:
            total = total + self.kde(name).log_prob(values[name])
        return total + np.log(self.class_probabilities()[np.asarray(values["class"], int)])

    def sample(self, rng: np.random.Generator, n: int) -> dict:
        """n draws of every property from the program's densities."""
        out = {name: self.kde(name).sample(rng, n) for name in CONTINUOUS}
        out["class"] = rng.choice(len(SHAPES), size=n, p=self.class_probabilities())
        return out


def _draws(source: ProtoProgram, config: DistanceConfig) -> dict:
    """The seeded draws x ~ P and log P(x) per property of the KL's first argument, and its class
    distribution: shared by every program P is compared with."""
    rng = np.random.default_rng(config.seed)
    side = {}
    for name in config.continuous:
        p = source.kde(name)
        x = p.sample(rng, config.samples)
        side[name] = (x, p.log_prob(x))
    side["class"] = source.class_probabilities(config.class_smoothing)
    return side


def _kl_matrix(class_programs: list[ProtoProgram], image_programs: list[ProtoProgram],
               config: DistanceConfig) -> dict:
    """Per property, the (images, classes) matrix of KL estimates in the configured direction.

    Every draw of the KL's first arguments is stacked, so each second argument's KDE is evaluated
    once per property for all of them together.
    """
    forward = config.direction == "class||image"
    sources, targets = (class_programs, image_programs) if forward else (image_programs, class_programs)
    sides = [_draws(source, config) for source in sources]
    n = config.samples
    terms = {}
    for name in config.continuous:
        x = np.concatenate([side[name][0] for side in sides])
        log_p = np.stack([side[name][1] for side in sides]).mean(axis=1)
        log_q = np.stack([target.kde(name).log_prob(x).reshape(len(sides), n).mean(axis=1) for target in targets])
        terms[name] = log_p[None, :] - log_q                               # (targets, sources)
    if "class" in config.properties:
        p = np.stack([side["class"] for side in sides])                    # (sources, shapes)
        q = np.stack([target.class_probabilities(config.class_smoothing) for target in targets])
        terms["class"] = np.sum(p * np.log(p), axis=1)[None, :] - np.log(q) @ p.T
    return terms if forward else {name: value.T for name, value in terms.items()}


def kl_terms(class_program: ProtoProgram, image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> dict:
    """The per-property KL terms of the module docstring (in ``config.direction``)."""
    matrix = _kl_matrix([class_program], [image_program], config)
    return {name: float(value[0, 0]) for name, value in matrix.items()}


def distance(class_program: ProtoProgram, image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> float:
    """d(C_k, C_I) = sum over properties of KL(C_k || C_I) (or KL(C_I || C_k), as ``config.direction`` says)."""
    return float(sum(kl_terms(class_program, image_program, config).values()))


def classify(class_programs: list[ProtoProgram], image_program: ProtoProgram,
             config: DistanceConfig = DistanceConfig()) -> np.ndarray:
    """p(c = k | I) over the given classes: softmax of the negative distances."""
    return classify_many(class_programs, [image_program], config)[0]


def classify_many(class_programs: list[ProtoProgram], image_programs: list[ProtoProgram],
                  config: DistanceConfig = DistanceConfig()) -> np.ndarray:
    """(images, classes) probabilities; each class's draws and densities are computed once."""
    distances = sum(_kl_matrix(class_programs, image_programs, config).values())
    return np.exp(log_softmax(-distances, axis=1))
