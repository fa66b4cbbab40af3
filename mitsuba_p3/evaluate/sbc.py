"""Simulation-based calibration: the sampler checked on data from its own model (Talts et al. 2018).

If scenes z are drawn from the prior, images I from the likelihood p(I | z), and the
sampler returns exact draws from p(z | I), then the rank of each true coordinate
among its L posterior draws is uniform on {0, ..., L}: the posterior draws and the
truth are exchangeable. A sampler that is too narrow piles ranks at both ends (a
U), one too wide in the middle (a hump), a biased one to one side.

Here z comes from the fitted prior (its shape class the argmax of the relaxed
one-hot, as the Gumbel-max trick makes it a draw of the class probabilities), the
image is the Phong render (hard shadows) plus Gaussian noise of the likelihood's
effective scale sigma / sqrt(beta) (:mod:`mitsuba_p3.fit.noise`). With power 1 and
that sigma the likelihood is exactly the model that made the image, and its
posterior is the tempered one inference uses, so the check is of the sampler, not
of the renderer's fit to real images.

Checked coordinates: the position (x, y), the log half-extents (3) and the colour
(RGB). Each gets a rank histogram and a chi-square test of uniformity over
``bins`` equal bins (p-value; small values flag a miscalibrated sampler). The
discrete part (the shape class) is checked by calibration: the ECE of the
posterior probability of the most probable class, and the mean probability
given to the true class beside the share of images where the mode is the truth.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .metrics import expected_calibration_error

CHECKED = ("shift_x", "shift_y", "log_scale_x", "log_scale_y", "log_scale_z", "colour_r", "colour_g", "colour_b")


def checked_values(x: dict) -> np.ndarray:
    """(..., 8) the checked coordinates of natural values (see :data:`CHECKED`)."""
    return np.concatenate([np.asarray(x["shift"]), np.log(np.asarray(x["scale"])), np.asarray(x["colour"])], axis=-1)


def rank_of(truth: np.ndarray, draws: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """(d,) ranks of ``truth`` (d,) among ``draws`` (L, d); ties (duplicated draws) broken at random, as
    SBC needs for samplers whose draws repeat."""
    below = np.sum(draws < truth, axis=0)
    ties = np.sum(draws == truth, axis=0)
    return below + rng.integers(0, ties + 1)


def uniformity(ranks: np.ndarray, draws: int, bins: int) -> tuple[np.ndarray, np.ndarray]:
    """Per column of ``ranks`` (n, d) in {0..draws}: counts per bin (bins, d) and the chi-square test's
    p-value of uniformity (d,)."""
    from scipy.stats import chisquare

    edges = np.linspace(0, draws + 1, bins + 1)
    counts = np.stack([np.histogram(ranks[:, j], edges)[0] for j in range(ranks.shape[1])], axis=1)
    return counts, np.array([chisquare(counts[:, j]).pvalue for j in range(counts.shape[1])])


@dataclass(frozen=True)
class SBCResult:
    ranks: np.ndarray             # (n, 8) ranks of the checked coordinates
    draws: int                    # L: posterior draws per image, ranks in {0..L}
    class_probabilities: np.ndarray   # (n, classes) posterior class probabilities
    true_class: np.ndarray        # (n,)

    def summary(self, bins: int = 10) -> dict:
        counts, p_values = uniformity(self.ranks, self.draws, bins)
        confidence = self.class_probabilities.max(axis=1)
        correct = self.class_probabilities.argmax(axis=1) == self.true_class
        ece, _ = expected_calibration_error(confidence, correct)
        p_true = self.class_probabilities[np.arange(len(self.true_class)), self.true_class]
        return {"images": int(len(self.ranks)), "draws": self.draws, "bins": bins,
                "rank_uniformity_p": {name: float(p) for name, p in zip(CHECKED, p_values)},
                "rank_counts": {name: counts[:, j].tolist() for j, name in enumerate(CHECKED)},
                "class": {"ece": ece, "accuracy": float(correct.mean()), "mean_confidence": float(confidence.mean()),
                          "mean_p_true": float(p_true.mean())}}


def simulate(core, rng: np.random.Generator) -> tuple[np.ndarray, dict, int]:
    """One scene from the prior and its image under the likelihood (see the module docstring):
    (image (H, W, 3), natural values, class index)."""
    import jax.numpy as jnp

    from ..space import render_params

    prior, config = core.prior, core.config
    z = prior.sample(rng, 1)[0].astype(np.float32)
    x = {k: np.asarray(v) for k, v in prior.constrain(jnp.asarray(z)).items()}
    clean = core.renderer.render({k: np.asarray(v) for k, v in render_params(x).items()})
    sigma = config.sigma / np.sqrt(config.power)
    image = clean + sigma * rng.standard_normal(clean.shape)
    return image.astype(np.float32), x, int(np.argmax(x["class_probabilities"]))


def run_sbc(core, sample, images: int, draws: int, seed: int = 0, cache=None, progress=None) -> SBCResult:
    """SBC of ``sample(observation, seed) -> (positions (L', 15), class probabilities)`` on ``images``
    simulations; ``core`` is a :class:`~mitsuba_p3.infer.model.PosteriorCore` whose likelihood has power 1
    (the model the images come from). Each image's ranks use ``draws`` of its posterior draws.

    Image i is simulated and sampled with seeds derived from (``seed``, i), so a run killed and started
    again with the same ``cache`` (an .npz path, rewritten atomically after every image) resumes where
    it stopped and gives the same result."""
    import jax.numpy as jnp

    from ..errors import ConfigError
    from ..files import atomic_npz

    if core.config.power != 1.0 or core.config.outlier != 0.0:
        raise ConfigError("SBC needs the likelihood the images are simulated from: power 1, no outliers")
    done = {"ranks": [], "probabilities": [], "truths": []}
    if cache is not None and cache.exists():
        with np.load(cache) as f:
            if int(f["draws"]) == draws and int(f["seed"]) == seed:
                done = {k: list(f[k]) for k in done}
    for i in range(len(done["ranks"]), images):
        rng = np.random.default_rng([seed, i])
        image, truth, cls = simulate(core, rng)
        positions, class_probabilities = sample(core.observe(image), int(rng.integers(2 ** 31)))
        chosen = positions[rng.choice(len(positions), size=draws, replace=len(positions) < draws)]
        values = checked_values({k: np.asarray(v) for k, v in core.prior.constrain(jnp.asarray(chosen)).items()})
        done["ranks"].append(rank_of(checked_values(truth), values, rng))
        done["probabilities"].append(np.asarray(class_probabilities, np.float64))
        done["truths"].append(cls)
        if cache is not None:
            atomic_npz(cache, draws=draws, seed=seed, **{k: np.array(v) for k, v in done.items()})
        if progress:
            progress(i + 1, images)
    return SBCResult(np.array(done["ranks"][:images]), draws, np.array(done["probabilities"][:images]),
                     np.array(done["truths"][:images]))
