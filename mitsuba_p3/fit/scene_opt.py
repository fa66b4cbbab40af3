"""Scene optimisation: fit the Phong world and the per-material parameters to a train split.

As in the paper's "Scene Optimization": geometry (shape, shift, yaw, size) is
fixed from the labels; the global parameters (point lights' positions and
intensities, floor colour, floor ambient and diffuse, the floor pattern) and
one Phong material per colour+material pair are fitted by Adam on the L2
image loss, one image per step, alternating passes that update only materials
with passes that update only the globals. Gradients come from Dr.Jit
(:meth:`MitsubaRenderer.loss_and_grad`).

Two deviations, stated. The shininess alpha is optimised as log(alpha), so a
learning rate of 0.01 can move it between rubber (~4) and metal (~40) within
the schedule; every other parameter is optimised directly and projected back
to its valid range after each step. And the lights are white by default
(``light_colour="white"``: one intensity per light, the same in each channel;
``"free"``, an RGB intensity per light, is the paper's). A light's colour
multiplies every material's fitted colour, so the images identify it only
through the white-weighted highlight and the floor; left free it drifts to a
tint that the class colours then cancel, and a gray metal's highlight renders
tinted. Held white, the benchmark's light tint goes into the fitted colours,
where the colour posterior reads it.

Four options beyond the paper, all off by default: ``observation="hemisphere"`` also fits the
environment's sky and ground radiance with the globals (:mod:`mitsuba_p3.render.hemisphere`),
``observation="microfacet"`` gives every surface the GGX microfacet lobe in place of Phong's highlight
(:mod:`mitsuba_p3.render.lobes`; the same parameters, so the rest of the pipeline is unchanged),
``light_radius`` widens every light into a disc for soft shadows (fixed, not fitted: visibility has
no gradient; :mod:`mitsuba_p3.render.soft_shadows`), and ``light_falloff`` gives the lights the inverse-square
falloff of physical lights (:mod:`mitsuba_p3.render.falloff`).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Callable

import numpy as np

from ..benchmarks.dataset import Dataset
from ..errors import ConfigError, FitError, check_counts, check_positive
from ..scene import Camera, Floor, PhongMaterial, PointLight, Scene, SceneObject
from ..render.lobes import OBSERVATION_LOBES
from ..shapes import shape_index

MATERIAL_KEYS = ("colour", "ambient", "diffuse", "specular", "shininess")
GLOBAL_KEYS = ("light_position", "light_intensity", "floor_colour", "floor_ambient", "floor_diffuse",
               "floor_pattern")
# the environment's two hemispheres, fitted with the globals under the hemisphere observation model
HEMISPHERE_KEYS = ("sky", "ground")
OBSERVATIONS = ("phong", "hemisphere", "microfacet")
# white: one intensity per light, the same in every channel (the default); free: each an RGB intensity (the paper's)
LIGHT_COLOURS = ("free", "white")
# where the sky and ground start (radiance, display units): a dim grey environment
INITIAL_HEMISPHERE = 0.05



@dataclass(frozen=True)
class SceneOptConfig:
    """The schedule and initialisation (defaults: the paper's, see PAPER_NOTES.md)."""

    epochs: int = 7
    material_passes: int = 5
    global_passes: int = 5
    learning_rate: float = 0.01
    lights: int = 5
    light_box: tuple = ((-0.5, 0.5), (-0.5, 0.5), (0.2, 0.8))  # initial positions, metres
    light_intensity: tuple = (0.1, 0.5)
    pattern_size: int = 200
    resolution: tuple = (120, 160)
    shadows: bool = True   # observations have shadows; fit the floor without baking them in
    light_radius: float = 0.0   # metres: lights widened into discs, soft shadows (0: the paper's point lights)
    # metres: the lights' inverse-square falloff about this reference distance (render/falloff.py; 0: none, the
    # paper's). The value only sets the unit of the fitted intensities (the light's at that distance): about
    # the lights' distance from the table keeps them at the paper's scale
    light_falloff: float = 0.0
    # phong: point lights and a constant ambient term (the paper's); hemisphere: also a fitted sky and ground
    # (render/hemisphere.py)
    observation: str = "phong"
    light_colour: str = "white"   # LIGHT_COLOURS (module docstring)
    seed: int = 777
    init_material: dict = field(default_factory=lambda: {"ambient": 0.1, "diffuse": 0.9, "specular": 0.5,
                                                         "shininess": 4.0})
    init_floor: dict = field(default_factory=lambda: {"colour": 0.5, "ambient": 0.1, "diffuse": 0.9})
    snapshots: int = 3     # train images whose render is kept after every epoch (figures)
    refine_materials: bool = True   # exact least squares on the material bases after Adam (fit/materials.py)

    def __post_init__(self):
        check_counts(self, {"epochs": 1, "material_passes": 0, "global_passes": 0, "lights": 1, "pattern_size": 1,
                            "seed": 0, "snapshots": 0}, "fit ")
        check_positive(self, ("learning_rate",), "fit ")
        if self.observation not in OBSERVATIONS:
            raise ConfigError(f"unknown observation model {self.observation!r}; choose {' or '.join(OBSERVATIONS)}")
        if self.light_colour not in LIGHT_COLOURS:
            raise ConfigError(f"unknown light colour {self.light_colour!r}; choose {' or '.join(LIGHT_COLOURS)}")
        if not (np.isfinite(self.light_radius) and 0.0 <= self.light_radius <= 0.5):
            raise ConfigError(f"fit light_radius must be in [0, 0.5] metres; got {self.light_radius}")
        if not (np.isfinite(self.light_falloff) and 0.0 <= self.light_falloff <= 10.0):
            raise ConfigError(f"fit light_falloff must be in [0, 10] metres (0: no falloff); got {self.light_falloff}")
        object.__setattr__(self, "resolution", tuple(self.resolution))
        if len(self.resolution) != 2 or min(self.resolution) < 1:
            raise ConfigError(f"fit resolution must be (height, width); got {self.resolution}")


def material_key(shot) -> str:
    """Materials are shared by colour and material name (size and shape do not matter)."""
    return f"{shot.cls.colour}-{shot.cls.material}"


def geometry_of(shot) -> dict[str, np.ndarray]:
    """The contract's object geometry for a labelled shot (the Phong frame has its base at z = 0)."""
    return {"shift": shot.position[:2].astype(np.float32), "theta": np.float32(shot.yaw),
            "scale": shot.scale.astype(np.float32), "kappa": np.int32(shape_index(shot.cls.shape))}


class Adam:
    """Adam on a dict of numpy arrays (one state per optimised group)."""

    def __init__(self, params: dict[str, np.ndarray], learning_rate: float, beta1=0.9, beta2=0.999, eps=1e-8):
        self.lr, self.b1, self.b2, self.eps = learning_rate, beta1, beta2, eps
        self.m = {k: np.zeros_like(v) for k, v in params.items()}
        self.v = {k: np.zeros_like(v) for k, v in params.items()}
        self.t = 0

    def step(self, params: dict[str, np.ndarray], grads: dict[str, np.ndarray]) -> None:
        self.t += 1
        for key, g in grads.items():
            self.m[key] = self.b1 * self.m[key] + (1 - self.b1) * g
            self.v[key] = self.b2 * self.v[key] + (1 - self.b2) * g * g
            m_hat = self.m[key] / (1 - self.b1 ** self.t)
            v_hat = self.v[key] / (1 - self.b2 ** self.t)
            params[key] = (params[key] - self.lr * m_hat / (np.sqrt(v_hat) + self.eps)).astype(np.float32)


def _project_material(m: dict[str, np.ndarray]) -> None:
    m["colour"] = np.clip(m["colour"], 0.0, 1.0)
    for key in ("ambient", "diffuse", "specular"):
        m[key] = np.maximum(m[key], 0.0)
    m["log_shininess"] = np.clip(m["log_shininess"], 0.0, np.log(500.0))


def _project_globals(g: dict[str, np.ndarray]) -> None:
    g["light_intensity"] = np.maximum(g["light_intensity"], 0.0)
    g["floor_colour"] = np.clip(g["floor_colour"], 0.0, 1.0)
    g["floor_ambient"] = np.maximum(g["floor_ambient"], 0.0)
    g["floor_diffuse"] = np.maximum(g["floor_diffuse"], 0.0)
    g["floor_pattern"] = np.clip(g["floor_pattern"], 0.0, 4.0)
    for key in HEMISPHERE_KEYS:
        g[key] = np.maximum(g[key], 0.0)


@dataclass
class SceneFit:
    """Fitted world and materials, the loss curve and the snapshots for figures."""

    globals: dict[str, np.ndarray]
    materials: dict[str, dict[str, float | list]]
    loss_curve: list[dict]            # one row per pass: epoch, phase, pass, mean loss
    final_loss: float                 # mean per-pixel squared error over the train split
    snapshots: dict[str, np.ndarray]  # "observations" (S,H,W,3), "renders" (E+1,S,H,W,3), "files"
    config: dict

    def scene(self) -> Scene:
        """The fitted Phong scene (protocol camera, fitted lights and floor; a placeholder object)."""
        g = self.globals
        lights = [PointLight(np.asarray(p, np.float64), np.asarray(i, np.float64))
                  for p, i in zip(g["light_position"], g["light_intensity"])]
        floor = Floor(PhongMaterial(np.asarray(g["floor_colour"], np.float64), float(g["floor_ambient"]),
                                    float(g["floor_diffuse"]), 0.0, 1.0),
                      pattern=np.asarray(g["floor_pattern"], np.float32), pattern_file="pattern.png")
        return Scene(camera=Camera(), lights=lights, ambient_light=np.ones(3), floor=floor,
                     object=SceneObject("sphere", np.zeros(2), 0.0, np.full(3, 0.035),
                                        PhongMaterial.named("gray", "rubber")),
                     light_radius=float(g.get("light_radius", 0.0)),
                     light_falloff=float(g.get("light_falloff", 0.0)),
                     sky=np.asarray(g.get("sky", np.zeros(3)), np.float64),
                     ground=np.asarray(g.get("ground", np.zeros(3)), np.float64),
                     lobe=OBSERVATION_LOBES[self.config.get("observation", "phong")])


def initial_globals(config: SceneOptConfig) -> dict[str, np.ndarray]:
    """The authors' initialisation, in metres: random lights above the table, a flat floor."""
    rng = np.random.default_rng(config.seed)
    box = np.asarray(config.light_box, np.float64)
    positions = rng.uniform(box[:, 0], box[:, 1], size=(config.lights, 3))
    intensities = rng.uniform(*config.light_intensity, size=(config.lights, 3))
    if config.light_colour == "white":
        intensities = np.repeat(intensities[:, :1], 3, axis=1)
    f = config.init_floor
    return {
        "light_position": positions.astype(np.float32),
        "light_intensity": intensities.astype(np.float32),
        "floor_colour": np.full(3, f["colour"], np.float32),
        "floor_ambient": np.float32(f["ambient"]),
        "floor_diffuse": np.float32(f["diffuse"]),
        # Floor albedo = colour x pattern, so the pattern starts at ones (zeros would be black).
        "floor_pattern": np.ones((config.pattern_size, config.pattern_size, 3), np.float32),
        "light_radius": np.float32(config.light_radius),   # fixed, not optimised (visibility has no gradient)
        "light_falloff": np.float32(config.light_falloff),  # fixed: the model's choice, not a fitted value
        **{key: np.full(3, INITIAL_HEMISPHERE if config.observation == "hemisphere" else 0.0, np.float32)
           for key in HEMISPHERE_KEYS},
    }


def initial_material(shot, config: SceneOptConfig) -> dict[str, np.ndarray]:
    m = config.init_material
    return {"colour": (np.asarray(shot.cls.rgb, np.float32) / 255.0),
            "ambient": np.float32(m["ambient"]), "diffuse": np.float32(m["diffuse"]),
            "specular": np.float32(m["specular"]), "log_shininess": np.float32(np.log(m["shininess"]))}


def _contract_material(m: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {"colour": m["colour"], "ambient": m["ambient"], "diffuse": m["diffuse"],
            "specular": m["specular"], "shininess": np.float32(np.exp(m["log_shininess"]))}


def optimise_scene(dataset: Dataset, config: SceneOptConfig | None = None,
                   progress: Callable[[int, int, float], None] | None = None) -> SceneFit:
    """Fit lights, floor and materials to ``dataset``'s train split (see the module docstring).

    ``progress(step, total_steps, running_loss)`` is called after every step.
    """
    from ..backend import mitsuba
    from ..render import make_renderer

    config = config or SceneOptConfig()
    mi = mitsuba()
    shots = dataset.split("train")
    if not shots:
        raise FitError(f"{dataset.root}: no train images to fit (ood reuses the fsclvr fit)")
    height, width = config.resolution
    if tuple(dataset.resolution) != (height, width):
        raise FitError(f"the data set is loaded at {dataset.resolution}, the fit runs at {config.resolution}")

    globals_ = initial_globals(config)
    materials = {}
    for shot in shots:
        materials.setdefault(material_key(shot), initial_material(shot, config))
    scene = SceneFit(globals_, {}, [], 0.0, {}, asdict(config)).scene()
    renderer = make_renderer(scene, "mitsuba", height=height, width=width, shadows=config.shadows)

    targets = [mi.Float(dataset.image(shot).reshape(-1)) for shot in shots]
    geometry = [geometry_of(shot) for shot in shots]
    keys = [material_key(shot) for shot in shots]
    material_adam = {k: Adam(v, config.learning_rate) for k, v in materials.items()}
    global_adam = Adam(globals_, config.learning_rate)
    rng = np.random.default_rng(config.seed)
    snapshot_ids = list(np.linspace(0, len(shots) - 1, min(config.snapshots, len(shots))).astype(int))

    def params_for(i: int) -> dict[str, np.ndarray]:
        return {**globals_, **geometry[i], **_contract_material(materials[keys[i]])}

    def snapshot() -> np.ndarray:
        return np.stack([renderer.render(params_for(i)) for i in snapshot_ids])

    renders = [snapshot()]
    curve = []
    passes_per_epoch = config.material_passes + config.global_passes
    total = config.epochs * passes_per_epoch * len(shots)
    step = 0
    material_keys = list(MATERIAL_KEYS)
    global_keys = GLOBAL_KEYS + (HEMISPHERE_KEYS if config.observation == "hemisphere" else ())
    for epoch in range(config.epochs):
        for pass_index in range(passes_per_epoch):
            phase = "materials" if pass_index < config.material_passes else "globals"
            losses = []
            for i in rng.permutation(len(shots)):
                if phase == "materials":
                    loss, grads = renderer.loss_and_grad(params_for(i), targets[i], material_keys)
                    m = materials[keys[i]]
                    grads["log_shininess"] = grads.pop("shininess") * np.exp(m["log_shininess"])
                    material_adam[keys[i]].step(m, grads)
                    _project_material(m)
                else:
                    loss, grads = renderer.loss_and_grad(params_for(i), targets[i], global_keys)
                    if config.light_colour == "white":   # the gradient along the grey axis keeps lights white
                        grads["light_intensity"] = np.repeat(
                            grads["light_intensity"].mean(axis=-1, keepdims=True), 3, axis=-1)
                    global_adam.step(globals_, grads)
                    _project_globals(globals_)
                losses.append(loss)
                step += 1
                if progress:
                    progress(step, total, float(np.mean(losses)))
            curve.append({"epoch": epoch, "phase": phase, "pass": pass_index, "loss": float(np.mean(losses))})
        renders.append(snapshot())

    if config.refine_materials:
        from .materials import refine_materials

        members = {key: [i for i in range(len(shots)) if keys[i] == key] for key in materials}
        refined, _ = refine_materials(
            renderer, {key: np.stack([dataset.image(shots[i]) for i in m]) for key, m in members.items()},
            {key: [params_for(i) for i in m] for key, m in members.items()},
            {key: _contract_material(m) for key, m in materials.items()})
        for key, m in refined.items():
            materials[key] = {"colour": np.asarray(m["colour"], np.float32), "ambient": np.float32(m["ambient"]),
                              "diffuse": np.float32(m["diffuse"]), "specular": np.float32(m["specular"]),
                              "log_shininess": np.float32(np.log(m["shininess"]))}

    final = float(np.mean([np.mean((renderer.render(params_for(i)) - dataset.image(shot)) ** 2)
                           for i, shot in enumerate(shots)]))
    if config.refine_materials:
        curve.append({"epoch": config.epochs, "phase": "refinement", "pass": 0, "loss": final})
    fitted = {k: {name: np.asarray(v).tolist() for name, v in _contract_material(m).items()}
              for k, m in materials.items()}
    snapshots = {"observations": np.stack([dataset.image(shots[i]) for i in snapshot_ids]),
                 "renders": np.stack(renders), "files": np.array([str(shots[i].file) for i in snapshot_ids])}
    return SceneFit(globals_, fitted, curve, final, snapshots, asdict(config))
