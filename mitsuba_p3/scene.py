"""Scene description: Camera, PointLight, PhongMaterial, Floor, SceneObject, Scene.

A :class:`Scene` is plain data. It converts to the renderer contract
(:meth:`Scene.params`, a flat mapping of named arrays) and to and from Mitsuba
XML. The XML files are genuine Mitsuba scenes (``mi.load_file`` renders them
with the project's ``phong`` BSDF and ``phong_integrator``); the object's knobs are ``<default>``
values at the top of the file, so a person edits them by hand, or overrides them
like Mitsuba's ``-D name=value``.
"""
from __future__ import annotations

import dataclasses
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path
from typing import Mapping

import numpy as np

from .errors import SceneError
from .shapes import PARTS, SHAPES, shape_index

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

    def validate(self) -> "Scene":
        """Check every value; raise :class:`SceneError` naming the first bad one."""
        if not self.lights:
            raise SceneError("the scene has no point light")
        for i, light in enumerate(self.lights):
            light.position = _vector(light.position, 3, f"light {i} position")
            light.intensity = _vector(light.intensity, 3, f"light {i} intensity", 0.0)
        self.ambient_light = _vector(self.ambient_light, 3, "ambient light", 0.0)
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


# --------------------------------------------------------------------------- XML

OBJECT_DEFAULTS = ("shape", "shift_x", "shift_y", "theta_deg", "scale",
                   "colour", "ambient", "diffuse", "specular", "shininess")


def _fmt(values) -> str:
    arr = np.atleast_1d(np.asarray(values, dtype=np.float64))
    return ", ".join(f"{v:.6g}" for v in arr)


def _el(parent, tag, **attrs):
    return ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items()})


def _phong_bsdf_xml(parent, bsdf_id: str, colour: str, ambient: str, diffuse: str, specular: str,
                    shininess: str, pattern_file: str | None = None):
    bsdf = _el(parent, "bsdf", type="phong", id=bsdf_id)
    _el(bsdf, "rgb", name="colour", value=colour)
    for name, value in (("ambient", ambient), ("diffuse", diffuse), ("specular", specular),
                        ("shininess", shininess)):
        _el(bsdf, "float", name=name, value=value)
    if pattern_file:
        tex = _el(bsdf, "texture", type="bitmap", name="pattern")
        _el(tex, "string", name="filename", value=pattern_file)
        _el(tex, "boolean", name="raw", value="true")
    return bsdf


def scene_to_xml(scene: Scene, description: str = "") -> str:
    """The Mitsuba XML text of a scene (see :func:`save_scene` for the pattern file)."""
    scene.validate()
    obj, cam, floor = scene.object, scene.camera, scene.floor
    root = ET.Element("scene", version="3.0.0")
    defaults = {
        "shape": obj.shape, "shift_x": _fmt(obj.shift[0]), "shift_y": _fmt(obj.shift[1]),
        "theta_deg": _fmt(np.degrees(obj.theta)), "scale": _fmt(obj.scale),
        "colour": _fmt(obj.material.colour), "ambient": _fmt(obj.material.ambient),
        "diffuse": _fmt(obj.material.diffuse), "specular": _fmt(obj.material.specular),
        "shininess": _fmt(obj.material.shininess),
    }
    for name in OBJECT_DEFAULTS:
        _el(root, "default", name=name, value=defaults[name])

    integrator = _el(root, "integrator", type="phong_integrator")
    _el(integrator, "rgb", name="ambient", value=_fmt(scene.ambient_light))
    _el(integrator, "boolean", name="shadows", value=str(bool(scene.shadows)).lower())

    sensor = _el(root, "sensor", type="perspective")
    _el(sensor, "float", name="fov", value=_fmt(cam.fov))
    _el(sensor, "string", name="fov_axis", value="y")
    tr = _el(sensor, "transform", name="to_world")
    _el(tr, "lookat", origin=_fmt(cam.origin), target=_fmt(cam.target), up=_fmt(cam.up))
    film = _el(sensor, "film", type="hdrfilm")
    _el(film, "integer", name="width", value=cam.width)
    _el(film, "integer", name="height", value=cam.height)
    _el(film, "rfilter", type="box")

    for i, light in enumerate(scene.lights):
        em = _el(root, "emitter", type="point", id=f"light_{i}")
        _el(em, "point", name="position", value=_fmt(light.position))
        _el(em, "rgb", name="intensity", value=_fmt(light.intensity))

    fm = floor.material
    _phong_bsdf_xml(root, "floor-material", _fmt(fm.colour), _fmt(fm.ambient), _fmt(fm.diffuse),
                    _fmt(fm.specular), _fmt(fm.shininess),
                    floor.pattern_file if floor.pattern is not None else None)
    rect = _el(root, "shape", type="rectangle", id="floor")
    tr = _el(rect, "transform", name="to_world")
    _el(tr, "scale", value=_fmt([floor.half_size, floor.half_size, 1.0]))
    _el(rect, "ref", id="floor-material")

    _phong_bsdf_xml(root, "object-material", "$colour", "$ambient", "$diffuse", "$specular", "$shininess")
    for name in SHAPES:
        group = _el(root, "shape", type="shapegroup", id=name)
        for part in PARTS[name]:
            shape = _el(group, "shape", type=part.type)
            for key, value in part.props.items():
                _el(shape, "point" if isinstance(value, tuple) else "float", name=key, value=_fmt(value))
            if part.translate != (0.0, 0.0, 0.0) or part.scale != (1.0, 1.0, 1.0):
                tr = _el(shape, "transform", name="to_world")
                if part.scale != (1.0, 1.0, 1.0):
                    _el(tr, "scale", value=_fmt(part.scale))
                if part.translate != (0.0, 0.0, 0.0):
                    _el(tr, "translate", value=_fmt(part.translate))
            _el(shape, "ref", id="object-material")
    inst = _el(root, "shape", type="instance", id="object")
    _el(inst, "ref", id="$shape")
    tr = _el(inst, "transform", name="to_world")
    _el(tr, "scale", value="$scale")
    _el(tr, "rotate", z="1", angle="$theta_deg")
    _el(tr, "translate", value="$shift_x, $shift_y, 0")

    ET.indent(root, space="    ")
    header = (
        "<?xml version=\"1.0\" encoding=\"utf-8\"?>\n"
        "<!-- mitsuba-p3 scene" + (f": {description}" if description else "") + "\n"
        "     A genuine Mitsuba 3 scene for the project's phong_integrator and phong BSDF.\n"
        "     Units are metres, z is up, the floor is z = 0. The object's knobs are the\n"
        "     <default> values below (theta_deg: yaw about z in degrees; scale: the three\n"
        "     half-extents; shape: sphere, cube or cylinder); edit them, or override them\n"
        "     from the command line (mitsuba-p3 render FILE, option set NAME=VALUE).\n"
        "     Point lights follow the Phong model: no distance fall-off. -->\n"
    )
    return header + ET.tostring(root, encoding="unicode") + "\n"


def save_scene(scene: Scene, path: str | Path, description: str = "") -> Path:
    """Write a scene as Mitsuba XML; a floor pattern is written as a PNG beside it."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    floor = scene.floor
    if floor.pattern is not None:
        if not floor.pattern_file:
            floor.pattern_file = f"textures/{path.stem}_floor.png"
        from .images import write_png

        write_png(path.parent / floor.pattern_file, floor.pattern)
    path.write_text(scene_to_xml(scene, description))
    return path


_SUBST = re.compile(r"\$(\w+)")


def _substitute(root: ET.Element, values: Mapping[str, str], source: str) -> None:
    def repl(match):
        name = match.group(1)
        if name not in values:
            raise SceneError(f"{source}: ${name} is used but no <default name=\"{name}\"> defines it")
        return values[name]

    for el in root.iter():
        for key, value in el.attrib.items():
            if "$" in value:
                el.set(key, _SUBST.sub(repl, value))


def _props(el: ET.Element) -> dict[str, ET.Element]:
    return {child.get("name"): child for child in el if child.get("name")}


def _by_id(root: ET.Element) -> dict[str, ET.Element]:
    """Defined objects by id (``<ref id=...>`` points at one, it does not define one)."""
    return {el.get("id"): el for el in root.iter() if el.get("id") and el.tag != "ref"}


def _material_from_xml(bsdf: ET.Element, source: str, what: str) -> PhongMaterial:
    if bsdf.get("type") != "phong":
        raise SceneError(f"{source}: the {what} must use <bsdf type=\"phong\">, found {bsdf.get('type')!r}")
    p = _props(bsdf)
    default = PhongMaterial()
    get = lambda name, d: p[name].get("value") if name in p else d  # noqa: E731
    try:
        return PhongMaterial(
            colour=_vector(get("colour", default.colour), 3, f"{what} colour", 0.0, 1.0),
            ambient=_number(get("ambient", default.ambient), f"{what} ambient", 0.0),
            diffuse=_number(get("diffuse", default.diffuse), f"{what} diffuse", 0.0),
            specular=_number(get("specular", default.specular), f"{what} specular", 0.0),
            shininess=_number(get("shininess", default.shininess), f"{what} shininess", 0.0),
        )
    except SceneError as exc:
        raise SceneError(f"{source}: {exc}") from None


def _bsdf_of(shape: ET.Element, ids: dict, source: str, what: str) -> ET.Element:
    for child in shape:
        if child.tag == "bsdf":
            return child
        if child.tag == "ref" and ids.get(child.get("id")) is not None and ids[child.get("id")].tag == "bsdf":
            return ids[child.get("id")]
    raise SceneError(f"{source}: the {what} has no <bsdf> (or <ref> to one)")


def _parse_transform(tr: ET.Element | None, source: str, what: str) -> dict[str, np.ndarray]:
    out: dict[str, np.ndarray] = {}
    if tr is None:
        return out
    for step in tr:
        if step.tag == "scale":
            v = step.get("value")
            out["scale"] = _vector(v, 3, f"{what} scale") if v is not None else np.array(
                [float(step.get(a, 1.0)) for a in "xyz"])
        elif step.tag == "translate":
            v = step.get("value")
            out["translate"] = _vector(v, 3, f"{what} translate") if v is not None else np.array(
                [float(step.get(a, 0.0)) for a in "xyz"])
        elif step.tag == "rotate":
            axis = np.array([float(step.get(a, 0.0)) for a in "xyz"])
            if not np.allclose(axis, [0, 0, 1]):
                raise SceneError(f"{source}: the {what} may only rotate about z (yaw), got axis {axis.tolist()}")
            out["theta"] = np.radians(_number(step.get("angle"), f"{what} rotate angle"))
        else:
            raise SceneError(f"{source}: the {what} transform may use scale, rotate (z) and translate, "
                             f"not <{step.tag}>")
    return out


def load_scene(path: str | Path, overrides: Mapping[str, object] | None = None) -> Scene:
    """Read a scene XML file; ``overrides`` replace ``<default>`` values by name.

    Raises :class:`SceneError` naming the file for malformed XML, unknown shapes,
    bad values and missing texture files.
    """
    path = Path(path)
    source = str(path)
    if not path.is_file():
        raise SceneError(f"{source}: no such scene file")
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"{source}: malformed XML ({exc}); fix the file or regenerate it") from None
    if root.tag != "scene":
        raise SceneError(f"{source}: the root element must be <scene>, found <{root.tag}>")

    values = {el.get("name"): el.get("value") for el in root.findall("default")}
    for name, value in (overrides or {}).items():
        if name not in values:
            raise SceneError(f"{source}: cannot set {name!r}; the file's <default> names are "
                             f"{', '.join(values) or 'none'}")
        values[name] = value if isinstance(value, str) else _fmt(value)
    _substitute(root, values, source)
    ids = _by_id(root)

    scene = Scene()
    integrator = root.find("integrator")
    if integrator is not None:
        if integrator.get("type") != "phong_integrator":
            raise SceneError(f"{source}: <integrator type=\"phong_integrator\"> expected, found {integrator.get('type')!r}")
        p = _props(integrator)
        if "ambient" in p:
            scene.ambient_light = _vector(p["ambient"].get("value"), 3, "ambient light", 0.0)
        if "shadows" in p:
            scene.shadows = p["shadows"].get("value", "false").lower() == "true"

    sensor = root.find("sensor")
    if sensor is None:
        raise SceneError(f"{source}: no <sensor>; add the protocol camera")
    p = _props(sensor)
    cam = scene.camera
    cam.fov = _number(p["fov"].get("value"), "camera fov") if "fov" in p else cam.fov
    axis = p["fov_axis"].get("value") if "fov_axis" in p else "x"
    lookat = sensor.find("transform/lookat")
    if lookat is None:
        raise SceneError(f"{source}: the sensor needs <transform name=\"to_world\"><lookat .../></transform>")
    cam.origin = _vector(lookat.get("origin"), 3, "camera origin")
    cam.target = _vector(lookat.get("target"), 3, "camera target")
    cam.up = _vector(lookat.get("up", "0, 0, 1"), 3, "camera up")
    film = sensor.find("film")
    if film is not None:
        fp = _props(film)
        cam.width = int(fp["width"].get("value")) if "width" in fp else 768
        cam.height = int(fp["height"].get("value")) if "height" in fp else 576
    if axis == "x":  # convert to the vertical field of view used throughout
        half = np.radians(cam.fov) / 2
        cam.fov = float(np.degrees(2 * np.arctan(np.tan(half) * cam.height / cam.width)))
    elif axis != "y":
        raise SceneError(f"{source}: sensor fov_axis must be 'x' or 'y', found {axis!r}")

    scene.lights = []
    for em in root.findall("emitter"):
        if em.get("type") != "point":
            raise SceneError(f"{source}: only <emitter type=\"point\"> lights are part of the Phong model, "
                             f"found {em.get('type')!r}")
        p = _props(em)
        if "position" not in p or "intensity" not in p:
            raise SceneError(f"{source}: a point light needs 'position' and 'intensity'")
        scene.lights.append(PointLight(
            _vector(p["position"].get("value"), 3, "light position"),
            _vector(p["intensity"].get("value"), 3, "light intensity", 0.0)))

    floor_el = ids.get("floor")
    if floor_el is None or floor_el.get("type") != "rectangle":
        raise SceneError(f"{source}: no <shape type=\"rectangle\" id=\"floor\">")
    floor_bsdf = _bsdf_of(floor_el, ids, source, "floor")
    scene.floor.material = _material_from_xml(floor_bsdf, source, "floor")
    tf = _parse_transform(floor_el.find("transform"), source, "floor")
    scale = tf.get("scale", np.ones(3))
    if not np.isclose(scale[0], scale[1]) or "theta" in tf or np.any(tf.get("translate", np.zeros(3)) != 0):
        raise SceneError(f"{source}: the floor must be a square centred at the origin (scale x = y only)")
    scene.floor.half_size = float(scale[0])
    pattern = floor_bsdf.find("texture[@name='pattern']")
    if pattern is not None:
        fname = _props(pattern).get("filename")
        if fname is None:
            raise SceneError(f"{source}: the floor pattern texture needs a 'filename'")
        rel = fname.get("value")
        from .images import read_png

        file = path.parent / rel
        if not file.is_file():
            raise SceneError(f"{source}: floor pattern texture {file} does not exist; "
                             "fix the path or remove the <texture name=\"pattern\">")
        scene.floor.pattern = read_png(file)
        scene.floor.pattern_file = rel

    inst = ids.get("object")
    if inst is None or inst.get("type") != "instance":
        raise SceneError(f"{source}: no <shape type=\"instance\" id=\"object\">")
    ref = inst.find("ref")
    shape_name = ref.get("id") if ref is not None else None
    if shape_name not in SHAPES:
        raise SceneError(f"{source}: unknown shape {shape_name!r}; choose one of {', '.join(SHAPES)}")
    group = ids.get(shape_name)
    if group is None or group.get("type") != "shapegroup" or group.find("shape") is None:
        raise SceneError(f"{source}: the shape group {shape_name!r} is missing")
    material = _material_from_xml(_bsdf_of(group.find("shape"), ids, source, "object"), source, "object")
    tf = _parse_transform(inst.find("transform"), source, "object")
    translate = tf.get("translate", np.zeros(3))
    if abs(translate[2]) > 1e-9:
        raise SceneError(f"{source}: the object rests on the floor; its translate z must be 0, got {translate[2]}")
    scene.object = SceneObject(shape_name, translate[:2], float(tf.get("theta", 0.0)),
                               tf.get("scale", np.ones(3)), material)
    try:
        return scene.validate()
    except SceneError as exc:
        raise SceneError(f"{source}: {exc}") from None
