"""Scenes to and from Mitsuba XML.

The XML files are genuine Mitsuba scenes (``mi.load_file`` renders them with the
project's ``phong`` BSDF and ``phong_integrator``); the object's knobs are
``<default>`` values at the top of the file (:data:`~.model.OBJECT_DEFAULTS`), so a
person edits them by hand, or overrides them like Mitsuba's ``-D name=value``.
"""
from __future__ import annotations

import re
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Mapping

import numpy as np

from ..errors import SceneError
from ..files import atomic_write
from ..shapes import PARTS, SHAPES
from .model import OBJECT_DEFAULTS, PhongMaterial, PointLight, Scene, SceneObject, _number, _vector, fmt


def _el(parent, tag, **attrs):
    return ET.SubElement(parent, tag, {k: str(v) for k, v in attrs.items()})


def _phong_bsdf_xml(parent, bsdf_id: str, colour: str, ambient: str, diffuse: str, specular: str,
                    shininess: str, pattern_file: str | None = None, lobe: str = "phong"):
    bsdf = _el(parent, "bsdf", type="phong", id=bsdf_id)
    if lobe != "phong":
        _el(bsdf, "string", name="lobe", value=lobe)
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
        "shape": obj.shape, "shift_x": fmt(obj.shift[0]), "shift_y": fmt(obj.shift[1]),
        "theta_deg": fmt(np.degrees(obj.theta)), "scale": fmt(obj.scale),
        "colour": fmt(obj.material.colour), "ambient": fmt(obj.material.ambient),
        "diffuse": fmt(obj.material.diffuse), "specular": fmt(obj.material.specular),
        "shininess": fmt(obj.material.shininess),
    }
    for name in OBJECT_DEFAULTS:
        _el(root, "default", name=name, value=defaults[name])

    integrator = _el(root, "integrator", type="phong_integrator")
    _el(integrator, "rgb", name="ambient", value=fmt(scene.ambient_light))
    _el(integrator, "boolean", name="shadows", value=str(bool(scene.shadows)).lower())
    if scene.light_radius > 0:
        _el(integrator, "float", name="light_radius", value=fmt(scene.light_radius))
    if scene.light_falloff > 0:
        _el(integrator, "float", name="light_falloff", value=fmt(scene.light_falloff))
    if np.any(scene.sky > 0) or np.any(scene.ground > 0):
        _el(integrator, "rgb", name="sky", value=fmt(scene.sky))
        _el(integrator, "rgb", name="ground", value=fmt(scene.ground))

    sensor = _el(root, "sensor", type="perspective")
    _el(sensor, "float", name="fov", value=fmt(cam.fov))
    _el(sensor, "string", name="fov_axis", value="y")
    tr = _el(sensor, "transform", name="to_world")
    _el(tr, "lookat", origin=fmt(cam.origin), target=fmt(cam.target), up=fmt(cam.up))
    film = _el(sensor, "film", type="hdrfilm")
    _el(film, "integer", name="width", value=cam.width)
    _el(film, "integer", name="height", value=cam.height)
    _el(film, "rfilter", type="box")

    for i, light in enumerate(scene.lights):
        em = _el(root, "emitter", type="point", id=f"light_{i}")
        _el(em, "point", name="position", value=fmt(light.position))
        _el(em, "rgb", name="intensity", value=fmt(light.intensity))

    fm = floor.material
    _phong_bsdf_xml(root, "floor-material", fmt(fm.colour), fmt(fm.ambient), fmt(fm.diffuse),
                    fmt(fm.specular), fmt(fm.shininess),
                    floor.pattern_file if floor.pattern is not None else None, scene.lobe)
    rect = _el(root, "shape", type="rectangle", id="floor")
    tr = _el(rect, "transform", name="to_world")
    _el(tr, "scale", value=fmt([floor.half_size, floor.half_size, 1.0]))
    _el(rect, "ref", id="floor-material")

    _phong_bsdf_xml(root, "object-material", "$colour", "$ambient", "$diffuse", "$specular", "$shininess",
                    lobe=scene.lobe)
    for name in SHAPES:
        group = _el(root, "shape", type="shapegroup", id=name)
        for part in PARTS[name]:
            shape = _el(group, "shape", type=part.type)
            for key, value in part.props.items():
                _el(shape, "point" if isinstance(value, tuple) else "float", name=key, value=fmt(value))
            if part.translate != (0.0, 0.0, 0.0) or part.scale != (1.0, 1.0, 1.0):
                tr = _el(shape, "transform", name="to_world")
                if part.scale != (1.0, 1.0, 1.0):
                    _el(tr, "scale", value=fmt(part.scale))
                if part.translate != (0.0, 0.0, 0.0):
                    _el(tr, "translate", value=fmt(part.translate))
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
        from ..images import write_png

        write_png(path.parent / floor.pattern_file, floor.pattern)
    atomic_write(path, scene_to_xml(scene, description))
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
        values[name] = value if isinstance(value, str) else fmt(value)
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
        if "light_radius" in p:
            scene.light_radius = _number(p["light_radius"].get("value"), "light radius", 0.0)
        if "light_falloff" in p:
            scene.light_falloff = _number(p["light_falloff"].get("value"), "light falloff distance", 0.0)
        for name in ("sky", "ground"):
            if name in p:
                setattr(scene, name, _vector(p[name].get("value"), 3, f"{name} radiance", 0.0))

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
    lobe = floor_bsdf.find("string[@name='lobe']")
    scene.lobe = lobe.get("value", "phong") if lobe is not None else "phong"
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
        from ..images import read_png

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
    # the renderers draw the project's own primitives: a group edited into other geometry would be
    # ignored without a word, so it is refused
    for name in SHAPES:
        found = ids.get(name)
        if found is None or found.get("type") != "shapegroup":
            continue
        types = [child.get("type") for child in found.findall("shape")]
        expected = [part.type for part in PARTS[name]]
        if types != expected:
            raise SceneError(f"{source}: the shape group {name!r} must hold the parts "
                             f"{' + '.join(expected)}, found {' + '.join(map(str, types)) or 'none'}; the renderers "
                             "draw only the three primitives (move, scale or recolour the object instead)")
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
