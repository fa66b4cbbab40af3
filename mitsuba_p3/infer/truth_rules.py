"""Attribute rules a model carries for ``infer`` alone: learnt from the material at train images' true poses.

A posterior names its object's material kind and colour by rules (:class:`~mitsuba_p3.fit.attributes.
AttributeRules`). Learnt from the fit's own materials, they compare a posterior's medians with a
different kind of input: one material per train class, optimised under the fit's squared error, where
a posterior reads each image under the default likelihood (the shading fields). A start of the fit can
tint a fitted material so that a posterior's brown metal lies nearer the fit's red rubber. ``evaluate`` therefore learns its
rules from train posteriors; a lone ``infer`` has none.

What it can have at the cost of a minute: the material's conditional posterior at the *labelled* pose
and shape of a few train images per class, drawn by the sampler's own material moves (the Gibbs update
of colour and weights, :meth:`~mitsuba_p3.infer.material_moves.MaterialMoves.material_move`, one render
of the material bases per move) under the default P3 likelihood and scoring window, from the fit's
material of the image's class (its shininess kept). The material rule (on the Phong weights, the
reflectance's saturation and the image's Phong misfit at its labelled pose, :mod:`mitsuba_p3.infer.misfit`:
``evaluate``'s features, the misfit measured where a posterior's estimate would be) and the colour
centres are then learnt from those draws as ``evaluate`` learns them from posteriors. Chosen on train
classes, each class held out.

``mitsuba-p3 fit`` writes them to the model folder (:data:`~mitsuba_p3.fit.attributes.LEARNT_RULES_FILE`,
with the digest of the fit they were learnt for), and :func:`~mitsuba_p3.fit.attributes.rules_for` reads
them wherever the fit's rules were read.
"""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import numpy as np

from ..benchmarks.dataset import Dataset
from ..files import atomic_json, file_digest, folder_lock
from ..fit.attributes import LEARNT_RULES_FILE, rules_for
from ..fit.model import FittedModel
from ..fit.scene_opt import geometry_of
from ..shapes import SHAPES
from .misfit import misfit_renderer, model_misfit

IMAGES = 2          # train images per class
MOVES = 40          # material moves per image
BURN = 10           # moves dropped at the start
FEATURES = "weights+saturation+misfit"   # evaluate's rule's (MATERIAL_RULE_FEATURES), the misfit at the labelled pose
_NATURAL = ("colour", "ambient", "diffuse", "specular", "shininess")


class TruthSampler:
    """Material draws at a train image's labelled pose, under a fitted model's default P3 likelihood."""

    def __init__(self, fitted: FittedModel, resolution: tuple[int, int]):
        import jax

        from .likelihood import DEFAULT_NOISE
        from .model import PosteriorCore
        from .posterior import default_likelihood
        from .smc_config import SMCConfig

        self.fitted = fitted
        self.core = core = PosteriorCore.shared(fitted, default_likelihood(fitted, "p3", noise=DEFAULT_NOISE),
                                                "mitsuba", *resolution)
        self.window = SMCConfig().window
        self._move = jax.jit(lambda key, state, observation: core.material_move(key, state, observation))
        self._logdensity = jax.jit(lambda z, observation: core.logdensity(z, observation))

    def start(self, shot) -> np.ndarray:
        """z at the shot's labelled geometry and its class's fitted material."""
        geometry = geometry_of(shot)
        material = self.fitted.materials[f"{shot.cls.colour}-{shot.cls.material}"]
        x = {"shift": geometry["shift"][None].astype(np.float64), "theta": np.array([float(geometry["theta"])]),
             "scale": geometry["scale"][None].astype(np.float64),
             "class_probabilities": (np.eye(len(SHAPES))[int(geometry["kappa"])] * 0.998 + 0.001)[None],
             "colour": np.clip(np.asarray(material["colour"], np.float64), 1e-3, 1 - 1e-3)[None],
             **{name: np.array([float(material[name])]) for name in _NATURAL[1:]}}
        return self.core.prior.unconstrain(x)[0]

    def __call__(self, image: np.ndarray, shot, moves: int = MOVES, burn: int = BURN, seed: int = 0) -> dict:
        """{colour, ambient, diffuse, specular, shininess: draws} of the material at ``shot``'s pose."""
        import jax
        import jax.numpy as jnp
        from blackjax.mcmc.random_walk import RWState

        if not 0 <= burn < moves:
            raise ValueError(f"burn must lie in [0, moves); got {burn} of {moves}")
        window = self.core.window_for(image, tuple(self.window)) if self.window else None
        observation = self.core.observe(image, window) if window else self.core.observe(image)
        z = jnp.asarray(self.start(shot), jnp.float32)
        state = RWState(z, self._logdensity(z, observation))
        key, kept = jax.random.PRNGKey(seed), []
        for step in range(moves):
            key, sub = jax.random.split(key)
            state, _ = self._move(sub, state, observation)
            if step >= burn:
                kept.append(np.asarray(state.position))
        values = self.core.prior.constrain(jnp.asarray(np.stack(kept)))
        return {name: np.asarray(values[name]) for name in _NATURAL}


def truth_draws(fitted: FittedModel, dataset: Dataset, images: int = IMAGES, moves: int = MOVES, burn: int = BURN,
                progress: Callable[[int, int], None] | None = None) -> list[tuple[str, dict]]:
    """(class name, draws) for the first ``images`` train images of every train class whose colour and
    kind the fit has a material for; each draws' ``misfit`` is the image's Phong misfit at its labelled
    pose (:func:`~mitsuba_p3.infer.misfit.model_misfit`)."""
    shots = []
    for name in dataset.classes("train"):
        own = [s for s in dataset.shots_of(name) if f"{s.cls.colour}-{s.cls.material}" in fitted.materials]
        shots += own[:images]
    sampler = TruthSampler(fitted, dataset.resolution) if shots else None
    renderer = misfit_renderer(fitted, *dataset.resolution) if shots else None
    out = []
    for done, shot in enumerate(shots):
        image = dataset.image(shot)
        draws = sampler(image, shot, moves, burn, seed=shot.index)
        draws["misfit"] = model_misfit(fitted, image, geometry_of(shot), renderer)
        out.append((shot.class_name, draws))
        if progress:
            progress(done + 1, len(shots))
    return out


def rules_from_draws(rules, draws: list[tuple[str, dict]], labels: dict, features: str = FEATURES):
    """``rules`` with the material rule (on ``features``) and the colour centres learnt from (class name,
    draws) pairs, as ``evaluate`` learns them from posteriors; ``labels`` give each class's colour and kind."""
    if not draws:
        return rules
    samples = [d for _, d in draws]
    kinds = [labels[name].material for name, _ in draws]
    misfits = [d.get("misfit") for d in samples] if features.endswith("+misfit") else None
    rules = rules.with_material_from_posteriors(samples, kinds, features, misfits)
    return rules.with_colours_from_posteriors(samples, [labels[name].colour for name, _ in draws], kinds)


def learn_truth_rules(fitted: FittedModel, dataset: Dataset, images: int = IMAGES, moves: int = MOVES,
                      burn: int = BURN, progress: Callable[[int, int], None] | None = None):
    """The fit's own rules (:func:`~mitsuba_p3.fit.attributes.rules_for`) with the material rule and the
    colour centres learnt from :func:`truth_draws`."""
    return rules_from_draws(rules_for(fitted, dataset, learnt=False),
                            truth_draws(fitted, dataset, images, moves, burn, progress), dataset.class_labels)


def write_truth_rules(model_dir: str | Path, dataset_dir: str | Path, images: int = IMAGES, moves: int = MOVES,
                      burn: int = BURN, progress: Callable[[int, int], None] | None = None) -> Path:
    """Learn :func:`learn_truth_rules` for the fitted model in ``model_dir`` on the data set it was fitted
    to (``dataset_dir``, read at the fit's resolution) and write them there
    (:data:`~mitsuba_p3.fit.attributes.LEARNT_RULES_FILE`, with the digest of the model.json they were
    learnt for). Needs the fit's scene, priors and noise stages."""
    from ..benchmarks.dataset import load_dataset
    from ..errors import FitError

    root = Path(model_dir)
    with folder_lock(root, "mitsuba-p3 fit"):
        fitted = FittedModel(root)
        stages = fitted.info.get("stages", {})
        missing = [s for s in ("scene", "priors", "noise") if s not in stages]
        if missing:
            raise FitError(f"{root}: the attribute rules at the true pose need the fit's {', '.join(missing)} "
                           f"stage(s); run them first (mitsuba-p3 fit DATASET --out {root} --stages ...)")
        dataset = load_dataset(dataset_dir, resolution=tuple(stages["scene"]["config"]["resolution"]))
        rules = learn_truth_rules(fitted, dataset, images, moves, burn, progress)
        record = {**rules.material_record(), "model_digest": file_digest(root / "model.json"),
                  "source": {"images_per_class": images, "moves": moves, "burn": burn,
                             "what": "the material's conditional posterior at train images' labelled poses"}}
        return atomic_json(root / LEARNT_RULES_FILE, record)
