"""Render a benchmark with Blender Cycles from CLEVR's own asset files.

The paper's benchmarks were made by CLEVR's generator: Blender Cycles, CLEVR's
``base_scene.blend`` (ground, three area lamps and a sun), its ``Rubber`` and
``MyMetal`` node groups and its bevelled shapes. This module renders the project's
protocol (classes, splits, shots, poses and labels of :func:`.protocol.plan`) that
way, so a model can be fitted and tested on images another path tracer made.

How the protocol maps onto CLEVR's scene:

==================  ==========================================================
 unit               one Blender unit is ``METRES_PER_UNIT`` metres: CLEVR's
                    large objects (half-extent 0.7) are the protocol's
                    (0.035 m)
 camera             the protocol's (origin (0, -0.5, 0.35), vertical field of
                    view 42.5 degrees); CLEVR's ground, lamps and sun are turned
                    about z so that they stand where they stood around CLEVR's
                    own camera; CLEVR's camera jitter is not applied (the
                    protocol's camera is fixed)
 lamps              CLEVR's, each moved per image by U(-jitter, jitter) on each
                    axis (CLEVR's jitter, 1.0 unit), their strengths times the
                    world's ``lamp_strength``
 objects            CLEVR's shape files scaled by the half-extents, turned by
                    the yaw, resting on the ground; the material a copy of
                    CLEVR's node group with ``Color`` set to the colour's sRGB
                    values over 255, as CLEVR's generator sets it
 render             Cycles with the world's samples (CLEVR: 512) and bounces,
                    glossy blur 2.0, Blender's "Standard" view transform
==================  ==========================================================

A world is a small JSON file (``scenes/benchmarks/VARIANT.cycles.json``): lamp
strength, samples, and for ``room`` a textured floor and walls in the protocol's
metres. ``bpy`` (Blender as a Python module) is an optional dependency
(``pip install mitsuba-p3[blender]``); nothing here is imported unless this
renderer is asked for.
"""
from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..errors import BenchmarkError

WORLDS = Path(__file__).resolve().parents[2] / "scenes" / "benchmarks"
METRES_PER_UNIT = 0.05
# the protocol's camera (BENCHMARK.md), metres
CAMERA_ORIGIN = (0.0, -0.5, 0.35)
CAMERA_FOV_Y_DEG = 42.5
# the asset files a CLEVR folder must hold (its image_generation/data)
ASSET_FILES = ("base_scene.blend", "shapes/SmoothCube_v2.blend", "shapes/SmoothCylinder.blend",
               "shapes/Sphere.blend", "materials/Rubber.blend", "materials/MyMetal.blend")
SHAPE_FILES = {"cube": "SmoothCube_v2", "sphere": "Sphere", "cylinder": "SmoothCylinder"}
MATERIAL_GROUPS = {"rubber": "Rubber", "metal": "MyMetal"}
LAMPS = ("Lamp_Key", "Lamp_Fill", "Lamp_Back")


@dataclass(frozen=True)
class Surface:
    """A textured or plain rectangle of the world (floor or wall), in the protocol's metres."""

    centre: tuple[float, float, float]
    size: tuple[float, float]           # full width and height of the rectangle
    rotation_deg: tuple[float, float, float] = (0.0, 0.0, 0.0)   # Euler XYZ
    texture: str | None = None          # an image beside the world file
    repeat: float = 1.0                 # texture repeats across the rectangle
    rgb: tuple[float, float, float] = (0.5, 0.5, 0.5)            # linear reflectance without texture


@dataclass(frozen=True)
class CyclesWorld:
    """What a Cycles benchmark world sets; read from a JSON file by :func:`load_world`."""

    name: str
    lamp_strength: float = 1.0          # every CLEVR lamp (and the sun) times this
    lamp_jitter: float = 1.0            # CLEVR's per-image lamp jitter, Blender units per axis
    samples: int = 512
    max_bounces: int = 8
    clevr_ground: bool = True           # False: CLEVR's ground is hidden (the world's surfaces replace it)
    surfaces: tuple[Surface, ...] = field(default_factory=tuple)
    folder: Path = WORLDS

    def as_dict(self) -> dict:
        out = {k: getattr(self, k) for k in ("name", "lamp_strength", "lamp_jitter", "samples", "max_bounces",
                                              "clevr_ground")}
        out["surfaces"] = [dict(s.__dict__) for s in self.surfaces]
        return out


def _number(where: str, value, low: float, high: float) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not low <= value <= high:
        raise BenchmarkError(f"{where}: must be a number in [{low:g}, {high:g}], not {value!r}")
    return float(value)


def _vector(where: str, value, n: int, low: float, high: float) -> tuple[float, ...]:
    if not isinstance(value, list) or len(value) != n:
        raise BenchmarkError(f"{where}: must be a list of {n} numbers, not {value!r}")
    return tuple(_number(f"{where}[{i}]", v, low, high) for i, v in enumerate(value))


def load_world(path: str | Path) -> CyclesWorld:
    """Read and check a Cycles world file; every field is optional but ``name``."""
    path = Path(path)
    try:
        raw = json.loads(path.read_text())
    except (OSError, UnicodeDecodeError, json.JSONDecodeError) as exc:
        raise BenchmarkError(f"{path}: not a readable JSON world ({exc})") from None
    if not isinstance(raw, dict) or not isinstance(raw.get("name"), str):
        raise BenchmarkError(f"{path}: a Cycles world is a JSON object with a \"name\"")
    known = {"name", "lamp_strength", "lamp_jitter", "samples", "max_bounces", "clevr_ground", "surfaces"}
    if unknown := sorted(set(raw) - known):
        raise BenchmarkError(f"{path}: unknown field(s) {', '.join(unknown)}; known: {', '.join(sorted(known))}")
    if not isinstance(raw.get("surfaces", []), list):
        raise BenchmarkError(f"{path}: surfaces must be a list of objects")
    surfaces = []
    for i, s in enumerate(raw.get("surfaces", [])):
        where = f"{path}: surfaces[{i}]"
        if not isinstance(s, dict):
            raise BenchmarkError(f"{where}: must be an object")
        texture = s.get("texture")
        if texture is not None:
            if not isinstance(texture, str) or Path(texture).is_absolute() or ".." in Path(texture).parts:
                raise BenchmarkError(f"{where}: texture must be a relative path below the world's folder, not {texture!r}")
            if not (path.parent / texture).is_file():
                raise BenchmarkError(f"{where}: no texture {texture} below {path.parent}")
        surfaces.append(Surface(centre=_vector(f"{where}.centre", s.get("centre"), 3, -10, 10),
                                size=_vector(f"{where}.size", s.get("size"), 2, 1e-3, 20),
                                rotation_deg=_vector(f"{where}.rotation_deg", s.get("rotation_deg", [0, 0, 0]), 3,
                                                     -360, 360),
                                texture=texture, repeat=_number(f"{where}.repeat", s.get("repeat", 1.0), 1e-3, 1e3),
                                rgb=_vector(f"{where}.rgb", s.get("rgb", [0.5, 0.5, 0.5]), 3, 0, 1)))
    ground = raw.get("clevr_ground", True)
    if not isinstance(ground, bool):
        raise BenchmarkError(f"{path}: clevr_ground must be true or false")
    return CyclesWorld(name=raw["name"],
                       lamp_strength=_number(f"{path}: lamp_strength", raw.get("lamp_strength", 1.0), 0, 100),
                       lamp_jitter=_number(f"{path}: lamp_jitter", raw.get("lamp_jitter", 1.0), 0, 10),
                       samples=int(_number(f"{path}: samples", raw.get("samples", 512), 1, 1 << 16)),
                       max_bounces=int(_number(f"{path}: max_bounces", raw.get("max_bounces", 8), 0, 1024)),
                       clevr_ground=ground, surfaces=tuple(surfaces), folder=path.parent)


def world_file(variant: str) -> Path:
    path = WORLDS / f"{variant}.cycles.json"
    if not path.is_file():
        have = ", ".join(sorted(p.name.split(".")[0] for p in WORLDS.glob("*.cycles.json")))
        raise BenchmarkError(f"the Cycles renderer has no world for {variant!r} (it has {have}); "
                             "give one with --world")
    return path


def check_assets(assets: str | Path | None) -> Path:
    """The CLEVR asset folder, refused in one line when a file is missing."""
    if assets is None:
        raise BenchmarkError("--renderer cycles needs --assets: the folder of CLEVR's asset files "
                             "(clevr-dataset-gen's image_generation/data)")
    root = Path(assets).expanduser().resolve()
    missing = [name for name in ASSET_FILES if not (root / name).is_file()]
    if missing:
        raise BenchmarkError(f"{assets}: not CLEVR's asset folder (missing {', '.join(missing)})")
    return root


def require_bpy():
    """Import ``bpy`` or say how to get it."""
    try:
        import bpy
    except ImportError:
        raise BenchmarkError("--renderer cycles needs Blender as a Python module: pip install "
                             "'mitsuba-p3[blender]' (bpy 4.2, Python 3.11)") from None
    return bpy


def clevr_turn(camera_location) -> float:
    """The turn about z (radians) that carries CLEVR's camera azimuth onto the protocol camera's."""
    clevr = math.atan2(camera_location[1], camera_location[0])
    ours = math.atan2(CAMERA_ORIGIN[1], CAMERA_ORIGIN[0])
    return ours - clevr


def rotate_z(point, angle: float) -> np.ndarray:
    c, s = math.cos(angle), math.sin(angle)
    x, y, z = point
    return np.array([c * x - s * y, s * x + c * y, z])


def lamp_offsets(world: CyclesWorld, image_seed: int) -> dict[str, np.ndarray]:
    """Each lamp's jitter (Blender units, CLEVR's frame) for one image, from its seed alone."""
    rng = np.random.default_rng([image_seed, 7])
    return {lamp: rng.uniform(-world.lamp_jitter, world.lamp_jitter, size=3) for lamp in LAMPS}


class CyclesRenderer:
    """Renders one protocol image at a time with Blender Cycles (``render(image, path)``)."""

    def __init__(self, assets: str | Path, world: CyclesWorld, height: int, width: int,
                 threads: int | None = None):
        self.bpy = require_bpy()
        self.assets = check_assets(assets)
        self.world = world
        self.height, self.width = height, width
        self.threads = threads or os.cpu_count() or 1
        with _quiet():
            self._open_base()
            objects = self.bpy.data.objects
            self._turn = clevr_turn(objects["Camera"].location)
            self._lamp_home = {name: np.array(objects[name].location) for name in LAMPS}

    def lamps(self, image) -> dict[str, list[float]]:
        """The lamp positions ``image`` is rendered with, in the protocol's frame and metres (its label)."""
        offsets = lamp_offsets(self.world, image.image_seed)
        return {f"light_{name.split('_')[1].lower()}_position":
                (rotate_z(self._lamp_home[name] + offsets[name], self._turn) * METRES_PER_UNIT).tolist()
                for name in LAMPS}

    # -- the scene of one image ------------------------------------------------------------------
    def _open_base(self):
        bpy = self.bpy
        bpy.ops.wm.open_mainfile(filepath=str(self.assets / "base_scene.blend"))
        for name in MATERIAL_GROUPS.values():
            with bpy.data.libraries.load(str(self.assets / "materials" / f"{name}.blend")) as (_, into):
                into.node_groups = [name]
        return bpy.context.scene

    def _settings(self, scene, seed: int) -> None:
        render, cycles = scene.render, scene.cycles
        render.engine = "CYCLES"
        render.resolution_x, render.resolution_y, render.resolution_percentage = self.width, self.height, 100
        render.threads_mode, render.threads = "FIXED", self.threads
        render.image_settings.file_format, render.image_settings.color_mode = "PNG", "RGB"
        render.image_settings.color_depth = "8"
        cycles.device = "CPU"
        cycles.samples = self.world.samples
        cycles.use_adaptive_sampling = False
        cycles.use_denoising = False
        cycles.max_bounces = self.world.max_bounces
        cycles.transparent_min_bounces = cycles.transparent_max_bounces = self.world.max_bounces
        cycles.blur_glossy = 2.0
        cycles.seed = seed % (2**31 - 1)
        scene.view_settings.view_transform = "Standard"
        self.bpy.data.worlds["World"].cycles.sample_as_light = True

    def _place_world(self, scene, image_seed: int) -> None:
        """Turn CLEVR's lamps, sun and ground about z, jitter the lamps, set the camera."""
        bpy = self.bpy
        objects = bpy.data.objects
        turn = self._turn
        offsets = lamp_offsets(self.world, image_seed)
        for name in ("Area", "Ground", *LAMPS):
            obj = objects[name]
            local = np.array(obj.location) + offsets.get(name, 0.0)
            obj.location = tuple(rotate_z(local, turn))
            obj.rotation_euler[2] += turn
            if obj.type == "LIGHT":
                obj.data.energy *= self.world.lamp_strength
        if not self.world.clevr_ground:
            objects["Ground"].hide_render = True
        camera = objects["Camera"]
        camera.location = tuple(v / METRES_PER_UNIT for v in CAMERA_ORIGIN)   # tracks CLEVR's Empty at the origin
        camera.data.sensor_fit = "VERTICAL"
        camera.data.angle_y = math.radians(CAMERA_FOV_Y_DEG)
        camera.data.shift_x = camera.data.shift_y = 0.0
        scene.camera = camera
        for i, surface in enumerate(self.world.surfaces):
            self._add_surface(f"surface_{i}", surface)

    def _add_surface(self, name: str, surface: Surface) -> None:
        bpy = self.bpy
        bpy.ops.mesh.primitive_plane_add(size=1.0)
        plane = bpy.context.active_object
        plane.name = name
        plane.scale = (surface.size[0] / METRES_PER_UNIT, surface.size[1] / METRES_PER_UNIT, 1.0)
        plane.rotation_euler = tuple(math.radians(a) for a in surface.rotation_deg)
        plane.location = tuple(v / METRES_PER_UNIT for v in surface.centre)
        material = bpy.data.materials.new(name)
        material.use_nodes = True
        nodes, links = material.node_tree.nodes, material.node_tree.links
        bsdf = nodes["Principled BSDF"]
        bsdf.inputs["Roughness"].default_value = 1.0
        bsdf.inputs["Specular IOR Level"].default_value = 0.0
        if surface.texture:
            image = nodes.new("ShaderNodeTexImage")
            image.image = bpy.data.images.load(str(self.world.folder / surface.texture))
            mapping, coords = nodes.new("ShaderNodeMapping"), nodes.new("ShaderNodeTexCoord")
            mapping.inputs["Scale"].default_value = (surface.repeat, surface.repeat, 1.0)
            links.new(coords.outputs["UV"], mapping.inputs["Vector"])
            links.new(mapping.outputs["Vector"], image.inputs["Vector"])
            links.new(image.outputs["Color"], bsdf.inputs["Base Color"])
        else:
            bsdf.inputs["Base Color"].default_value = (*surface.rgb, 1.0)
        plane.data.materials.append(material)

    def _add_object(self, image) -> None:
        """CLEVR's shape file, scaled, turned and placed as the planned pose says, with its material."""
        bpy = self.bpy
        name = SHAPE_FILES[image.cls.shape]
        with bpy.data.libraries.load(str(self.assets / "shapes" / f"{name}.blend")) as (_, into):
            into.objects = [name]
        obj = into.objects[0]
        bpy.context.scene.collection.objects.link(obj)
        pose = image.pose
        obj.scale = tuple(s / METRES_PER_UNIT for s in pose.scale)
        obj.rotation_euler = (0.0, 0.0, pose.yaw)
        obj.location = (pose.x / METRES_PER_UNIT, pose.y / METRES_PER_UNIT, pose.z / METRES_PER_UNIT)
        material = bpy.data.materials.new(f"{name}_material")
        material.use_nodes = True
        tree = material.node_tree
        output = next(n for n in tree.nodes if n.type == "OUTPUT_MATERIAL")
        group = tree.nodes.new("ShaderNodeGroup")
        group.node_tree = bpy.data.node_groups[MATERIAL_GROUPS[image.cls.material]]
        group.inputs["Color"].default_value = (*[c / 255.0 for c in image.cls.rgb], 1.0)
        tree.links.new(group.outputs["Shader"], output.inputs["Surface"])
        obj.data.materials.clear()
        obj.data.materials.append(material)

    def render(self, image, path: Path) -> None:
        """Render planned ``image`` to the PNG ``path`` (written by Blender to a temporary name, then
        renamed, so a killed render leaves no partial image under ``path``)."""
        with _quiet():
            scene = self._open_base()
            self._settings(scene, image.image_seed)
            self._place_world(scene, image.image_seed)
            self._add_object(image)
            path.parent.mkdir(parents=True, exist_ok=True)
            partial = path.with_name(f".{path.stem}.partial.png")
            scene.render.filepath = str(partial)
            self.bpy.ops.render.render(write_still=True)
        os.replace(partial, path)


class _quiet:
    """Blender prints a line per tile and file; send its stdout to /dev/null while it works."""

    def __enter__(self):
        import sys

        sys.stdout.flush()
        self._saved = os.dup(1)
        devnull = os.open(os.devnull, os.O_WRONLY)
        os.dup2(devnull, 1)
        os.close(devnull)

    def __exit__(self, *exc):
        os.dup2(self._saved, 1)
        os.close(self._saved)
