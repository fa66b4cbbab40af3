"""The scene as plain data: Camera, PointLight, PhongMaterial, Floor, SceneObject, Scene.

A :class:`Scene` converts to the renderer contract (:meth:`Scene.params`, a flat
mapping of named arrays); :mod:`.xml` reads and writes it as Mitsuba XML, whose
object knobs :func:`object_overrides` fills from a user's words.
"""
from __future__ import annotations

import dataclasses
import re
from dataclasses import dataclass, field

import numpy as np

from ..errors import SceneError
from ..shapes import shape_index

# CLEVR's colours (facebookresearch/clevr-dataset-gen), 0-255.
COLOURS: dict[str, tuple[int, int, int]] = {
    "gray": (87, 87, 87),
    "red": (173, 35, 35),
    "blue": (42, 75, 215),
    "green": (29, 105, 20),
    "brown": (129, 74, 25),
    "purple": (129, 38, 192),
    "cyan": (41, 208, 208),
    "yellow": (255, 238, 51),
}

# Phong stand-ins for CLEVR's two materials: (ambient, diffuse, specular, shininess).
MATERIALS: dict[str, tuple[float, float, float, float]] = {
    "rubber": (0.1, 0.9, 0.1, 4.0),
    "metal": (0.1, 0.4, 0.9, 40.0),
}

# BENCHMARK.md sizes: half-extents of small and large objects (metres).
SIZES: dict[str, float] = {"small": 0.0175, "large": 0.035}


def colour_rgb(name_or_rgb) -> np.ndarray:
    """RGB in [0, 1] from a CLEVR colour name, an 'r,g,b' string or a 3-sequence."""
    if isinstance(name_or_rgb, str):
        key = name_or_rgb.strip().lower().replace("grey", "gray")
        if key in COLOURS:
            return np.asarray(COLOURS[key], dtype=np.float64) / 255.0
        try:
            return _vector(name_or_rgb, 3, "colour", low=0.0, high=1.0)
        except SceneError:
            raise SceneError(f"unknown colour {name_or_rgb!r}; use one of {', '.join(COLOURS)} "
                             "or 'r,g,b' in [0, 1]") from None
    return _vector(name_or_rgb, 3, "colour", low=0.0, high=1.0)


def _vector(value, n: int, what: str, low=-np.inf, high=np.inf) -> np.ndarray:
    """Parse/validate a length-n finite vector ('a, b, c', one number, or a sequence)."""
    if isinstance(value, str):
        try:
            items = [float(v) for v in re.split(r"[,\s]+", value.strip()) if v]
        except ValueError:
            raise SceneError(f"{what}: cannot read numbers from {value!r}") from None
    else:
        items = np.atleast_1d(np.asarray(value, dtype=np.float64)).tolist()
    if len(items) == 1 and n > 1:
        items = items * n
    arr = np.asarray(items, dtype=np.float64)
    if arr.shape != (n,):
        raise SceneError(f"{what}: expected {n} numbers, got {value!r}")
    if not np.all(np.isfinite(arr)):
        raise SceneError(f"{what}: values must be finite, got {value!r}")
    if np.any(arr < low) or np.any(arr > high):
        raise SceneError(f"{what}: values must lie in [{low}, {high}], got {value!r}")
    return arr


def _number(value, what: str, low=-np.inf, high=np.inf) -> float:
    return float(_vector(value, 1, what, low, high)[0])


# the specular lobes a scene's surfaces may have (render/lobes.py evaluates them): Phong's highlight or GGX microfacets
LOBES = ("phong", "ggx")


def check_lobe(lobe: str) -> str:
    """``lobe`` if it is one of :data:`LOBES`, else a :class:`SceneError` naming them."""
    if lobe not in LOBES:
        raise SceneError(f"unknown specular lobe {lobe!r}; choose one of {', '.join(LOBES)}")
    return lobe

@dataclass
class Camera:
    """Pinhole camera; BENCHMARK.md's protocol camera by default (vertical fov)."""

    origin: np.ndarray = field(default_factory=lambda: np.array([0.0, -0.50, 0.35]))
    target: np.ndarray = field(default_factory=lambda: np.zeros(3))
    up: np.ndarray = field(default_factory=lambda: np.array([0.0, 0.0, 1.0]))
    fov: float = 42.5  # vertical field of view, degrees
    height: int = 480
    width: int = 640


@dataclass
class PointLight:
    """A Phong point light: position (m) and RGB intensity, no distance fall-off."""

    position: np.ndarray
    intensity: np.ndarray


@dataclass
class PhongMaterial:
    """Phong material: albedo ``colour`` and the ambient/diffuse/specular/shininess weights."""

    colour: np.ndarray = field(default_factory=lambda: np.full(3, 0.5))
    ambient: float = 0.1
    diffuse: float = 0.9
    specular: float = 0.5
    shininess: float = 4.0

    @classmethod
    def named(cls, colour, material: str) -> "PhongMaterial":
        """A material from a colour (name or RGB) and a material name (rubber, metal)."""
        if material not in MATERIALS:
            raise SceneError(f"unknown material {material!r}; choose one of {', '.join(MATERIALS)}")
        return cls(colour_rgb(colour), *MATERIALS[material])

    def validate(self, what: str) -> None:
        self.colour = _vector(self.colour, 3, f"{what} colour", 0.0, 1.0)
        for name in ("ambient", "diffuse", "specular"):
            setattr(self, name, _number(getattr(self, name), f"{what} {name}", 0.0))
        self.shininess = _number(self.shininess, f"{what} shininess", 0.0)


@dataclass
class Floor:
    """The floor plane z = 0, a square of half-size ``half_size`` (m).

    Its albedo is ``material.colour`` times the ``pattern`` texture (an (H, W, 3)
    array in [0, 1], or None for a plain floor).
    """

    material: PhongMaterial = field(default_factory=lambda: PhongMaterial(np.full(3, 0.5), 0.2, 0.8, 0.0, 1.0))
    pattern: np.ndarray | None = None
    pattern_file: str | None = None  # where the pattern came from / is written to, relative to the XML
    half_size: float = 1.0


@dataclass
class SceneObject:
    """The one object: shape class, shift (x, y) on the floor, yaw theta (rad), half-extents."""

    shape: str = "sphere"
    shift: np.ndarray = field(default_factory=lambda: np.zeros(2))
    theta: float = 0.0
    scale: np.ndarray = field(default_factory=lambda: np.full(3, 0.035))
    material: PhongMaterial = field(default_factory=PhongMaterial)

    def validate(self) -> None:
        shape_index(self.shape)
        self.shift = _vector(self.shift, 2, "object shift")
        self.theta = _number(self.theta, "object theta")
        self.scale = _vector(self.scale, 3, "object scale")
        if np.any(self.scale <= 0):
            raise SceneError(f"object scale must be positive half-extents, got {self.scale.tolist()}")
        self.material.validate("object")


@dataclass
class Scene:
    """Everything the Phong renderers need: camera, lights, ambient light, floor, object."""

    camera: Camera = field(default_factory=Camera)
    lights: list[PointLight] = field(default_factory=list)
    ambient_light: np.ndarray = field(default_factory=lambda: np.ones(3))
    floor: Floor = field(default_factory=Floor)
    object: SceneObject = field(default_factory=SceneObject)
    shadows: bool = False
    light_radius: float = 0.0   # metres; > 0 softens the shadows (render/soft_shadows.py)
    # metres; > 0: each light's intensity falls off as (light_falloff / distance)^2, so an intensity is the
    # light's at that distance (render/falloff.py); 0: no falloff, the paper's point lights
    light_falloff: float = 0.0
    # radiance of the environment above and below the horizon (render/hemisphere.py); 0: point lights only
    sky: np.ndarray = field(default_factory=lambda: np.zeros(3))
    ground: np.ndarray = field(default_factory=lambda: np.zeros(3))
    # the specular lobe of every surface: Phong's highlight or GGX microfacets (render/lobes.py)
    lobe: str = "phong"

    def validate(self) -> "Scene":
        """Check every value; raise :class:`SceneError` naming the first bad one."""
        if not self.lights:
            raise SceneError("the scene has no point light")
        for i, light in enumerate(self.lights):
            light.position = _vector(light.position, 3, f"light {i} position")
            light.intensity = _vector(light.intensity, 3, f"light {i} intensity", 0.0)
        self.ambient_light = _vector(self.ambient_light, 3, "ambient light", 0.0)
        self.light_radius = _number(self.light_radius, "light radius", 0.0)
        self.light_falloff = _number(self.light_falloff, "light falloff distance", 0.0)
        self.sky = _vector(self.sky, 3, "sky radiance", 0.0)
        self.ground = _vector(self.ground, 3, "ground radiance", 0.0)
        check_lobe(self.lobe)
        if self.lobe != "phong" and (np.any(self.sky > 0) or np.any(self.ground > 0)):
            raise SceneError(f"the sky and ground terms assume the Phong lobe; the {self.lobe} lobe has none")
        self.floor.material.validate("floor")
        self.floor.half_size = _number(self.floor.half_size, "floor half-size", 1e-6)
        if self.floor.pattern is not None:
            p = np.asarray(self.floor.pattern, dtype=np.float32)
            if p.ndim != 3 or p.shape[2] != 3 or not np.all(np.isfinite(p)):
                raise SceneError(f"floor pattern must be a finite (H, W, 3) array, got shape {p.shape}")
            self.floor.pattern = p
        self.object.validate()
        cam = self.camera
        if cam.height < 1 or cam.width < 1:
            raise SceneError(f"camera resolution must be positive, got {cam.height}x{cam.width}")
        if not 0 < cam.fov < 180:
            raise SceneError(f"camera fov must be in (0, 180) degrees, got {cam.fov}")
        return self

    def replace(self, **changes) -> "Scene":
        """A copy with top-level fields replaced (nested dataclasses are deep-copied)."""
        return dataclasses.replace(_deepcopy(self), **changes)

    def params(self) -> dict[str, np.ndarray]:
        """The renderer contract: a flat mapping of named float32/int32 arrays."""
        obj, floor = self.object, self.floor
        pattern = floor.pattern if floor.pattern is not None else np.ones((2, 2, 3))
        return {
            "shift": np.asarray(obj.shift, np.float32),
            "theta": np.float32(obj.theta),
            "scale": np.asarray(obj.scale, np.float32),
            "kappa": np.int32(shape_index(obj.shape)),
            "colour": np.asarray(obj.material.colour, np.float32),
            "ambient": np.float32(obj.material.ambient),
            "diffuse": np.float32(obj.material.diffuse),
            "specular": np.float32(obj.material.specular),
            "shininess": np.float32(obj.material.shininess),
            "light_position": np.array([l.position for l in self.lights], np.float32),
            "light_intensity": np.array([l.intensity for l in self.lights], np.float32),
            "light_radius": np.float32(self.light_radius),
            "light_falloff": np.float32(self.light_falloff),
            "sky": np.asarray(self.sky, np.float32),
            "ground": np.asarray(self.ground, np.float32),
            "ambient_light": np.asarray(self.ambient_light, np.float32),
            "floor_colour": np.asarray(floor.material.colour, np.float32),
            "floor_ambient": np.float32(floor.material.ambient),
            "floor_diffuse": np.float32(floor.material.diffuse),
            "floor_specular": np.float32(floor.material.specular),
            "floor_shininess": np.float32(floor.material.shininess),
            "floor_pattern": np.asarray(pattern, np.float32),
        }


def _deepcopy(obj):
    import copy

    return copy.deepcopy(obj)


# The object's knobs: the <default> names at the top of a scene XML.
OBJECT_DEFAULTS = ("shape", "shift_x", "shift_y", "theta_deg", "scale",
                   "colour", "ambient", "diffuse", "specular", "shininess")


def fmt(values) -> str:
    """Numbers as a scene file writes them: ``"0.1, 0.2, 0.3"``."""
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    return ", ".join(f"{v:.6g}" for v in arr)


def object_overrides(shape: str | None = None, colour: str | None = None, material: str | None = None,
                     shift: str | None = None, theta: float | None = None, scale: str | None = None,
                     sets: list[str] | None = None) -> dict[str, str]:
    """A scene file's ``<default>`` overrides from a user's words: ``shape="cube"``, ``colour="red"``
    or ``"r,g,b"``, ``material="metal"``, ``shift="x,y"`` (m), ``theta`` (degrees), ``scale="small"``,
    one half-extent or ``"sx,sy,sz"``, and raw ``NAME=VALUE`` items in ``sets``."""
    out: dict[str, str] = {}
    for item in sets or []:
        if "=" not in item:
            raise SceneError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        out[name.strip()] = value.strip()
    if shape is not None:
        shape_index(shape)
        out["shape"] = shape
    if colour is not None:
        out["colour"] = fmt(colour_rgb(colour))
    if material is not None:
        if material not in MATERIALS:
            raise SceneError(f"unknown material {material!r}; choose one of {', '.join(MATERIALS)}")
        for name, value in zip(("ambient", "diffuse", "specular", "shininess"), MATERIALS[material]):
            out[name] = fmt(value)
    if shift is not None:
        x, y = _vector(shift, 2, "--shift")
        out["shift_x"], out["shift_y"] = fmt(x), fmt(y)
    if theta is not None:
        out["theta_deg"] = fmt(theta)
    if scale is not None:
        values = [SIZES[scale]] * 3 if scale in SIZES else _vector(scale, 3, "--scale")
        if min(values) <= 0:
            raise SceneError(f"--scale must be positive half-extents, got {scale!r}")
        out["scale"] = fmt(values)
    return out
