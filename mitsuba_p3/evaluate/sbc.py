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

Under the shading fields' form (``noise="fields"``, :mod:`mitsuba_p3.fit.fields`) the
tempered density beta log p(r) is, but for its log-determinant's factor, the Gaussian of
covariance (sigma^2 I + B T B') / beta, so the model checked is that one: white noise of
sigma / sqrt(beta) everywhere, and on the scoring window fields drawn with the taus /
sqrt(beta) on the true object's pixels and the floor its shadow changes, at power 1. The
fields live on the window's coordinates, so the simulation picks the window (from the image
before the fields, as the sampler would) and the sampler scores that window.

Under the image's own noise scale (``noise="scaled"``, :mod:`mitsuba_p3.fit.fields`, "An image's own
scale") each simulation first draws its scale s^2 from the fitted inverse-gamma prior and multiplies
all its noise, white and fields, by s; the sampler integrates s^2 out at an effective count of one per
value (the model's own: the images are drawn from it, not tempered), and bridges it in after its search
under the fixed scale, as inference does. So the check covers the bridge and the scaled density too.

Checked coordinates: the position (x, y), the log half-extents (3) and the colour
(RGB). Each is reported the way the field's tools print it (the ``SBC`` R package, ``sbi``'s
``check_sbc``, ArviZ's ``plot_ecdf_pit``):

- the Kolmogorov-Smirnov test of the ranks' uniformity (:func:`ks_uniformity`: the ranks made
  continuous by a uniform jitter within their slot, which is exactly uniform on (0, 1) under a
  calibrated sampler), and the chi-square test over ``bins`` equal bins;
- the ECDF difference, the ranks' empirical CDF minus the uniform's, with **simultaneous** 95%
  bands (Säilynoja, Bürkner and Vehtari 2022; :func:`ecdf_bands`): a calibrated sampler's curve
  leaves the band somewhere in only 5% of SBC runs, where pointwise bands would be crossed by
  chance at many points at once. A U-shaped rank histogram (too narrow) is an S below then above
  zero; a shifted one a one-sided bulge;
- the rank histogram.

The discrete part (the shape class) is checked by calibration: the ECE of the posterior
probability of the most probable class, its reliability bins, and the mean probability given to
the true class beside the share of images where the mode is the truth.
"""
from __future__ import annotations

import dataclasses
import json
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


def pit_values(ranks: np.ndarray, draws: int, seed: int = 0) -> np.ndarray:
    """Ranks (n, d) in {0..L} as values in (0, 1): (rank + u) / (L + 1), u uniform; exactly uniform
    on (0, 1) when the ranks are uniform on {0..L} (a fixed ``seed``, so a report is reproducible)."""
    u = np.random.default_rng(seed).uniform(size=np.shape(ranks))
    return (np.asarray(ranks) + u) / (draws + 1)


def ks_uniformity(ranks: np.ndarray, draws: int) -> np.ndarray:
    """Per column of ``ranks`` (n, d) the Kolmogorov-Smirnov p-value of the ranks' uniformity (d,)."""
    from scipy.stats import kstest

    values = pit_values(ranks, draws)
    return np.array([kstest(values[:, j], "uniform").pvalue for j in range(values.shape[1])])


def ecdf_bands(n: int, points: int = 100, level: float = 0.95, simulations: int = 4000,
               seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Simultaneous ``level`` bands for the ECDF difference of ``n`` uniform values at ``points`` evenly
    spaced z in (0, 1): (z, lower, upper), as differences from z. The pointwise level gamma is adjusted
    by simulation (Säilynoja et al. 2022, their simulation method): for each of ``simulations`` uniform
    samples, the smallest two-sided binomial tail probability of its ECDF over the z; gamma is the
    (1 - level) quantile of those minima, and the band the binomial's gamma/2 and 1 - gamma/2 quantiles."""
    from scipy.stats import binom

    z = np.arange(1, points + 1) / (points + 1)
    rng = np.random.default_rng(seed)
    counts = np.stack([np.searchsorted(np.sort(rng.uniform(size=n)), z, side="right") for _ in range(simulations)])
    tails = 2 * np.minimum(binom.cdf(counts, n, z), binom.sf(counts - 1, n, z))
    gamma = float(np.quantile(np.minimum(tails, 1.0).min(axis=1), 1 - level))
    lower = binom.ppf(gamma / 2, n, z) / n - z
    upper = binom.ppf(1 - gamma / 2, n, z) / n - z
    return z, lower, upper


def ecdf_difference(ranks: np.ndarray, draws: int, z: np.ndarray) -> np.ndarray:
    """(points, d): each column's ECDF of its PIT values (:func:`pit_values`) at ``z``, minus z."""
    values = np.sort(pit_values(ranks, draws), axis=0)
    return np.stack([np.searchsorted(values[:, j], z, side="right") / len(values) for j in range(values.shape[1])],
                    axis=1) - z[:, None]


@dataclass(frozen=True)
class SBCResult:
    ranks: np.ndarray             # (n, 8) ranks of the checked coordinates
    draws: int                    # L: posterior draws per image, ranks in {0..L}
    class_probabilities: np.ndarray   # (n, classes) posterior class probabilities
    true_class: np.ndarray        # (n,)

    def summary(self, bins: int = 10) -> dict:
        """The report as JSON: per coordinate the KS and chi-square p-values, whether the ECDF difference
        stays inside its simultaneous 95% band, the rank counts; the shape posterior's calibration."""
        counts, p_values = uniformity(self.ranks, self.draws, bins)
        z, lower, upper = ecdf_bands(len(self.ranks))
        difference = ecdf_difference(self.ranks, self.draws, z)
        inside = np.all((difference >= lower[:, None] - 1e-12) & (difference <= upper[:, None] + 1e-12), axis=0)
        confidence = self.class_probabilities.max(axis=1)
        correct = self.class_probabilities.argmax(axis=1) == self.true_class
        ece, reliability = expected_calibration_error(confidence, correct)
        p_true = self.class_probabilities[np.arange(len(self.true_class)), self.true_class]
        return {"images": int(len(self.ranks)), "draws": self.draws, "bins": bins,
                "rank_uniformity_ks_p": {name: float(p) for name, p in zip(CHECKED, ks_uniformity(self.ranks,
                                                                                                   self.draws))},
                "rank_uniformity_p": {name: float(p) for name, p in zip(CHECKED, p_values)},
                "ecdf_inside_95_band": {name: bool(v) for name, v in zip(CHECKED, inside)},
                "ecdf_max_excursion": {name: float(np.max(np.abs(difference[:, j]))) for j, name in enumerate(CHECKED)},
                "rank_counts": {name: counts[:, j].tolist() for j, name in enumerate(CHECKED)},
                "class": {"ece": ece, "accuracy": float(correct.mean()), "mean_confidence": float(confidence.mean()),
                          "mean_p_true": float(p_true.mean()), "reliability": reliability}}


def simulate(core, rng: np.random.Generator) -> tuple[np.ndarray, dict, int]:
    """One scene from the prior and its image under the likelihood (see the module docstring):
    (image (H, W, 3), natural values, class index)."""
    return _simulate(core, rng)[:3]


def _simulate(core, rng: np.random.Generator):
    """:func:`simulate`'s image, natural values and class index, and the scene's unconstrained position
    and noiseless render."""
    import jax.numpy as jnp

    from ..space import render_params

    prior, config = core.prior, core.config
    z = prior.sample(rng, 1)[0].astype(np.float32)
    x = {k: np.asarray(v) for k, v in prior.constrain(jnp.asarray(z)).items()}
    clean = np.asarray(core.renderer.render({k: np.asarray(v) for k, v in render_params(x).items()}))
    # the image's own noise scale s, drawn from its inverse-gamma prior (1 where the likelihood fixes it)
    s = 1.0 if config.scale is None else float(np.sqrt(config.scale[1] / rng.gamma(config.scale[0])))
    sigma = s * config.sigma / np.sqrt(config.power)
    image = clean + sigma * rng.standard_normal(clean.shape)
    return image.astype(np.float32), x, int(np.argmax(x["class_probabilities"])), z, clean, s


def simulate_scored(core, rng: np.random.Generator, window: tuple[int, int] | None = None):
    """One simulation and where the sampler scores it: (image, natural values, class index, window).
    Under the fitted Gaussian, :func:`simulate`'s and no window (the sampler picks its own). Under the
    shading fields' form, the fields drawn on the ``window`` (height, width) that the white-noise image's
    footprint chooses (the whole image where none is given or fits), and that window (top, left, height,
    width), which the sampler must score: the fields live on its coordinates (module docstring)."""
    import jax.numpy as jnp

    image, truth, cls, z, clean, s = _simulate(core, rng)
    if core.config.fields is None:
        return image, truth, cls, None
    from ..fit.fields import sample_fields
    from ..infer.likelihood import fields_form, fields_masks, fields_regions

    where = (core.window_for(image, tuple(window)) if window else None) or (0, 0, *image.shape[:2])
    top, left, height, width = where
    observation = core.observe(image, where)
    objects = core.objects(jnp.asarray(z), observation)
    masks = fields_masks(jnp.asarray(clean[top:top + height, left:left + width]), objects, observation["empty"],
                         fields_regions(core.config))
    variances, basis, loading = fields_form(core.config, height, width,
                                            colours=np.asarray(core.params(jnp.asarray(z))["colour"]))
    image[top:top + height, left:left + width] += s * sample_fields(np.asarray(masks), variances, basis, rng,
                                                                    loading).astype(np.float32)
    return image, truth, cls, where


def simulate_and_rank(core, sample, seed: int, i: int, draws: int, window: tuple[int, int] | None = None):
    """Simulation ``i`` of an SBC run seeded by ``seed``, sampled by ``sample`` and ranked: the truth's ranks
    (8,) among ``draws`` posterior draws, the class probabilities and the true class. Everything random
    comes from the stream (``seed``, i), so a simulation can be drawn and sampled again on its own."""
    import jax.numpy as jnp

    rng = np.random.default_rng([seed, i])
    image, truth, cls, where = simulate_scored(core, rng, window)
    seed_i = int(rng.integers(2 ** 31))
    positions, class_probabilities = (sample(core.observe(image), seed_i) if where is None else
                                      sample(core.observe(image), seed_i, where))
    chosen = positions[rng.choice(len(positions), size=draws, replace=len(positions) < draws)]
    values = checked_values({k: np.asarray(v) for k, v in core.prior.constrain(jnp.asarray(chosen)).items()})
    return rank_of(checked_values(truth), values, rng), class_probabilities, cls


def run_sbc(core, sample, images: int, draws: int, seed: int = 0, cache=None, progress=None,
            tag: str = "{}", window: tuple[int, int] | None = None, simulations=None) -> SBCResult:
    """SBC of ``sample(observation, seed) -> (positions (L', 15), class probabilities)`` on ``images``
    simulations; ``core`` is a :class:`~mitsuba_p3.infer.model.PosteriorCore` whose likelihood has power 1
    (the model the images come from). Each image's ranks use ``draws`` of its posterior draws.

    Image i is simulated and sampled with seeds derived from (``seed``, i), so a run killed and started
    again with the same ``cache`` (an .npz path, rewritten atomically after every image) resumes where
    it stopped and gives the same result. ``tag`` names the sampler's settings; a cache made under other
    settings is refused rather than continued. ``simulations``: the indices to run -> (i, ranks, class
    probabilities, class) in any order (:func:`simulations_in_workers`), instead of one after another
    here; the cache keeps the simulations done without a gap, so a resumed run starts after them."""
    from ..errors import ConfigError
    from ..files import atomic_npz

    if core.config.power != 1.0 or core.config.outlier != 0.0:
        raise ConfigError("SBC needs the likelihood the images are simulated from: power 1, no outliers")
    done = {"ranks": [], "probabilities": [], "truths": []}
    if cache is not None and cache.exists():
        with np.load(cache) as f:
            made = str(f["tag"]) if "tag" in f else "{}"
            if made != tag:
                raise ConfigError(f"{cache} holds simulations of other sampler settings ({made}, not {tag}): "
                                  "choose another output folder")
            if int(f["draws"]) == draws and int(f["seed"]) == seed:
                done = {k: list(f[k]) for k in done}
    todo = range(len(done["ranks"]), images)
    finished = simulations(todo) if simulations is not None else \
        ((i, *simulate_and_rank(core, sample, seed, i, draws, window)) for i in todo)
    waiting = {}                        # finished after a simulation that is not yet: kept until it is
    for i, ranks, class_probabilities, cls in finished:
        waiting[i] = ranks, class_probabilities, cls
        while len(done["ranks"]) in waiting:
            ranks, class_probabilities, cls = waiting.pop(len(done["ranks"]))
            done["ranks"].append(ranks)
            done["probabilities"].append(np.asarray(class_probabilities, np.float64))
            done["truths"].append(cls)
            if cache is not None:
                atomic_npz(cache, draws=draws, seed=seed, tag=tag, **{k: np.array(v) for k, v in done.items()})
        if progress:
            progress(len(done["ranks"]) + len(waiting), images)
    return SBCResult(np.array(done["ranks"][:images]), draws, np.array(done["probabilities"][:images]),
                     np.array(done["truths"][:images]))


_WORKER_CORES: dict = {}


def simulation_job(model_dir: str, resolution: tuple[int, int], noise: str, config, seed: int, i: int, draws: int,
                   threads: int | None = None) -> tuple:
    """Simulation ``i`` in a worker process (a picklable job): (i, ranks, class probabilities, class). The
    worker keeps its core, and so the sampler compiled for it, for the simulations after its first."""
    if threads:
        from .jobs import _exit_with_parent, _limit_threads

        _exit_with_parent()
        _limit_threads(threads)
    key = (model_dir, tuple(resolution), noise)
    if key not in _WORKER_CORES:
        _WORKER_CORES[key] = model_core(model_dir, "mitsuba", tuple(resolution), noise)
    core = _WORKER_CORES[key]
    return (i, *simulate_and_rank(core, smc_sampler(core, config), seed, i, draws, config.window))


def simulations_in_workers(model_dir, resolution: tuple[int, int], noise: str, config, seed: int, draws: int,
                           jobs: int):
    """``run_sbc``'s ``simulations`` in ``jobs`` worker processes that live for the whole run, each with its
    share of the cores (one Dr.Jit thread and a single-threaded XLA on 2 cores and 2 jobs, as
    ``evaluate --jobs`` runs; :func:`~mitsuba_p3.evaluate.jobs.worker_threads`)."""
    from .jobs import in_workers, worker_threads

    threads = worker_threads(jobs)

    def simulations(todo):
        calls = [(str(model_dir), tuple(resolution), noise, config, seed, i, draws, threads) for i in todo]
        return in_workers(simulation_job, calls, jobs)

    return simulations


def smc_sampler(core, config):
    """The SBC's view of the SMC: observation, seed (and the window to score, where the simulation
    chose it) -> (positions, class probabilities)."""
    from dataclasses import replace

    from ..infer.evidence import shape_weights
    from ..infer.smc import sample_smc

    def sample(observation, seed, window=None):
        run = sample_smc(core, observation, replace(config, seed=seed), window=window)
        probabilities = np.array(list(shape_weights(run.statistics).values()))
        return run.positions.reshape(-1, run.positions.shape[-1]), probabilities

    return sample


def model_core(model_dir, renderer: str = "mitsuba", resolution: tuple[int, int] = (120, 160), noise: str = "fitted"):
    """The :class:`~mitsuba_p3.infer.model.PosteriorCore` of a fitted model whose likelihood is the one its
    own images are simulated from: the fitted Gaussian at sigma / sqrt(power), power 1 (``noise``:
    ``fitted``, the power 1 / correlation area, or ``sandwich``, the pose's), or the shading fields' form
    (``fields``) with its sigma divided by sqrt(power) and its taus as fitted (the likelihood's own form,
    :func:`~mitsuba_p3.infer.posterior.default_likelihood`), with the image's own scale integrated out under
    the fitted prior at one effective count per value (``scaled``; module docstring)."""
    from ..errors import FitError
    from ..fit.model import FittedModel
    from ..infer.likelihood import LikelihoodConfig
    from ..infer.model import PosteriorCore

    from ..errors import ConfigError

    if noise not in ("fitted", "sandwich", "fields", "scaled"):
        raise ConfigError(f"sbc simulates the fitted, sandwich, fields and scaled noise models; not {noise!r}")
    fitted = FittedModel(model_dir)
    model_noise = fitted.noise
    if noise in ("fields", "scaled"):
        from ..fit.fields import FieldsNoise

        if model_noise.fields is None:
            raise FitError(f"{model_dir} has no shading fields: refit its noise stage "
                           "(mitsuba-p3 fit ... --stages noise)")
        form = FieldsNoise.from_dict(model_noise.fields)
        if noise == "scaled" and form.scale is None:
            raise FitError(f"{model_dir} was fitted before the noise scale's prior: refit its noise stage "
                           "(mitsuba-p3 fit ... --stages noise)")
        likelihood = LikelihoodConfig("p3", sigma=form.white_sigma, fields=form.taus, fields_degree=form.degree,
                                      fields_channels=form.channels, shadows=model_noise.shadows,
                                      scale=(*form.scale, 1.0) if noise == "scaled" else None)
        return PosteriorCore(fitted, likelihood, renderer, *resolution)
    power = model_noise.power if noise == "fitted" else model_noise.pose_power
    if power is None:
        raise FitError(f"{model_dir} has no sandwich power: refit its noise stage (mitsuba-p3 fit ... --stages noise)")
    likelihood = LikelihoodConfig("p3", sigma=model_noise.gaussian_sigma / np.sqrt(power), shadows=model_noise.shadows)
    return PosteriorCore(fitted, likelihood, renderer, *resolution)


def settings_tag(config) -> str:
    """An SBC cache's tag: the SMC settings that differ from the defaults of the first caches (whose tags
    name nothing else, :data:`~mitsuba_p3.infer.smc.DEFAULTS_BEFORE`), so a cache made before a default
    changed is not resumed under the new one."""
    from ..infer.smc import DEFAULTS_BEFORE

    defaults = {f.name: DEFAULTS_BEFORE.get(f.name, f.default) for f in dataclasses.fields(config)}
    return json.dumps({name: getattr(config, name) for name, default in defaults.items()
                       if getattr(config, name) != default and name != "seed"}, sort_keys=True)


def calibrate_model(model_dir, out, images: int = 200, draws: int = 99, resolution: tuple[int, int] = (120, 160),
                    seed: int = 0, noise: str = "fitted", progress=None, config=None, jobs: int = 1) -> dict:
    """SBC of the default sampler (tempered SMC) on a fitted model's own renders: ``images`` simulations
    from its prior, each rendered with its observation model plus the likelihood's noise at the effective
    sigma / sqrt(power) that inference uses (``noise``: the power 1 / correlation area, ``fitted``, the
    sandwich power along the pose, ``sandwich``, the shading fields' form, ``fields``, or that form with the
    image's own scale, ``scaled``); ``config``: the
    :class:`~mitsuba_p3.infer.smc.SMCConfig` (default: the default). Writes ``out/sbc.json``, ``sbc.png``,
    ``calibration.png`` and ``cache.npz``, from which a killed run resumes; returns the summary. ``jobs`` > 1
    runs the simulations in that many worker processes (:func:`simulations_in_workers`)."""
    from pathlib import Path

    from ..files import atomic_json
    from ..infer.smc import SMCConfig
    from ..plots import sbc_figures

    core, out = model_core(model_dir, "mitsuba", resolution, noise), Path(out)
    out.mkdir(parents=True, exist_ok=True)
    config = config or SMCConfig()
    # a cache of one noise form is not resumed under another (the fitted form's tags name none: the first caches')
    tag = settings_tag(config)
    if noise != "fitted":
        from ..fit.fields import POWER_ON
        from ..infer.bridge import SCALE_FORM

        # the fields' form records where its power acts (a cache of the earlier form has no such entry)
        form = {"noise": noise, **({"fields_power_on": POWER_ON} if noise in ("fields", "scaled") else {}),
                **({"scale_form": SCALE_FORM} if noise == "scaled" else {})}
        tag = json.dumps({**form, **json.loads(tag)}, sort_keys=True)
    simulations = simulations_in_workers(model_dir, resolution, noise, config, seed, draws, jobs) if jobs > 1 else None
    result = run_sbc(core, smc_sampler(core, config), images, draws, seed, cache=out / "cache.npz", progress=progress,
                     tag=tag, window=config.window, simulations=simulations)
    summary = {"model": str(model_dir), "noise": noise, "likelihood_sigma": core.config.sigma,
               "smc": dataclasses.asdict(config), **result.summary()}
    atomic_json(out / "sbc.json", summary)
    sbc_figures(summary, result, out / "sbc.png")
    return summary

