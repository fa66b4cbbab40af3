"""Render a benchmark with Mitsuba's path tracer into a data-set folder.

The world of each variant (camera, floor, walls, area lights, object materials
and shape groups) is the Mitsuba XML ``scenes/benchmarks/VARIANT.xml``; editing
it changes the benchmark, and an edited copy passed as ``world`` makes a new one
with the variant's classes and poses (files it names are looked for beside it,
then beside the shipped worlds). The generator only sets the XML's ``<default>`` knobs
for each image (object, material, colour, pose, light positions jittered by
``light_jitter``) and renders; a world's ``tone_curve`` knob chooses the camera's response
(:func:`tone_map`). Labels are planned first from the seed
(:func:`.protocol.plan`), written to ``labels.json``, and every image is written
atomically, so a killed generation resumes where it stopped.
"""
from __future__ import annotations

import json
import re
import shutil
import xml.etree.ElementTree as ET
from pathlib import Path
from typing import Callable

import numpy as np

from ..files import atomic_write
from .dataset import FORMAT, FORMAT_VERSION, LABELS_FILE, SCENE_FILE
from ..errors import BenchmarkError
from .protocol import (OOD_HALF_EXTENT, PlannedImage, check_size, check_variant, plan)

WORLDS = Path(__file__).resolve().parents[2] / "scenes" / "benchmarks"
# Per size: default resolution (H, W). Samples per pixel default to the XML's "spp"
# (full) or SMALL_SPP (small: the built-in example must take seconds).
DEFAULT_RESOLUTION = {"full": (480, 640), "small": (120, 160)}
SMALL_SPP = 32


def world_file(variant: str) -> Path:
    """The XML that describes a variant's world."""
    path = WORLDS / f"{check_variant(variant)}.xml"
    if not path.is_file():
        raise BenchmarkError(f"{path}: missing benchmark world; copy scenes/benchmarks/fsclvr.xml to "
                             f"{path.name} and edit it")
    return path


def read_defaults(path: Path) -> dict[str, str]:
    """The ``<default name=... value=...>`` knobs of a Mitsuba XML file."""
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise BenchmarkError(f"{path}: malformed XML ({exc})") from None
    return {el.get("name"): el.get("value") for el in root.findall("default")}


def srgb_encode(linear: np.ndarray) -> np.ndarray:
    """Linear radiance -> display sRGB in [0, 1] (the standard sRGB transfer curve)."""
    x = np.clip(np.asarray(linear, dtype=np.float64), 0.0, 1.0)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)


TONE_CURVES = ("none", "aces")


def tone_map(linear: np.ndarray, curve: str = "none") -> np.ndarray:
    """A camera's response to linear radiance, before the sRGB encoding: ``none`` leaves it to the
    encoding, which clips at 1 (what the Phong model assumes); ``aces`` is the filmic curve of film and
    of Blender's and game engines' defaults (Narkowicz's 2015 fit of ACES, exposure 0.6), which lifts the
    shadows and rolls highlights off instead of clipping them: an image pipeline other than the project's
    own. A world chooses it with ``<default name="tone_curve" value="aces"/>``."""
    x = np.asarray(linear, dtype=np.float64)
    if curve == "none":
        return x
    if curve == "aces":
        x = 0.6 * np.maximum(x, 0.0)
        return np.clip(x * (2.51 * x + 0.03) / (x * (2.43 * x + 0.59) + 0.14), 0.0, 1.0)
    raise BenchmarkError(f"tone_curve {curve!r}: choose one of {', '.join(TONE_CURVES)}")


def srgb_decode(display: np.ndarray) -> np.ndarray:
    """Display sRGB in [0, 1] -> linear reflectance."""
    x = np.asarray(display, dtype=np.float64)
    return np.where(x <= 0.04045, x / 12.92, np.power((x + 0.055) / 1.055, 2.4))


def _fmt(values) -> str:
    return ", ".join(f"{float(v):.6g}" for v in np.atleast_1d(values))


def light_positions(defaults: dict[str, str], rng: np.random.Generator) -> dict[str, list[float]]:
    """Each ``light_*_position`` default, jittered uniformly by +-``light_jitter`` metres per axis."""
    jitter = float(defaults.get("light_jitter", 0.0))
    out = {}
    for name in sorted(defaults):
        if name.startswith("light_") and name.endswith("_position"):
            nominal = np.array([float(v) for v in defaults[name].split(",")])
            out[name] = (nominal + rng.uniform(-jitter, jitter, size=3)).tolist()
    return out


def image_overrides(image: PlannedImage, defaults: dict[str, str]) -> tuple[dict[str, str], dict]:
    """The XML knobs for one image, and the light positions used (for its label)."""
    cls, pose = image.cls, image.pose
    mesh = cls.shape not in ("sphere", "cube", "cylinder")
    lights = light_positions(defaults, np.random.default_rng(image.image_seed))
    overrides = {
        "object": cls.shape,
        "material": cls.material,
        "colour": _fmt(srgb_decode(np.asarray(cls.rgb) / 255.0)),
        "scale": _fmt([OOD_HALF_EXTENT] * 3 if mesh else pose.scale),
        "theta_deg": _fmt(np.degrees(pose.yaw)),
        "shift": _fmt([pose.x, pose.y, pose.z]),
        **{name: _fmt(value) for name, value in lights.items()},
    }
    return overrides, lights


def label_of(image: PlannedImage, lights: dict) -> dict:
    """The labels.json record of an image (see the README's data-set format)."""
    cls, pose = image.cls, image.pose
    mesh = cls.shape not in ("sphere", "cube", "cylinder")
    matrix = pose.object_to_world((OOD_HALF_EXTENT,) * 3 if mesh else None)
    return {
        "file": image.file, "split": image.split, "shot": image.shot,
        "class": cls.as_dict(),
        "pose": {"x": pose.x, "y": pose.y, "z": pose.z, "yaw": pose.yaw, "scale": list(pose.scale),
                 "object_to_world": matrix.tolist()},
        "mesh": f"meshes/{cls.shape}.ply" if mesh else None,
        "lights": lights,
        "seed": image.image_seed,
    }


def _world_text(world: Path, height: int, width: int, spp: int) -> str:
    """The world XML with this run's resolution and samples per pixel."""
    text = world.read_text()
    for name, value in (("width", width), ("height", height), ("spp", spp)):
        text, n = re.subn(rf'(<default name="{name}" value=")[^"]*(")', rf"\g<1>{value}\g<2>", text)
        if n != 1:
            raise BenchmarkError(f"{world}: needs exactly one <default name=\"{name}\">")
    return text


def _copy_world(world: Path, out: Path, text: str) -> None:
    """Write the world XML into the data set with the files it references."""
    for relative in re.findall(r'<string name="filename" value="([^"$]+)"', text):
        target = out / relative
        source = next((folder / relative for folder in (world.parent, WORLDS) if (folder / relative).is_file()),
                      None)
        if source is None:
            raise BenchmarkError(f"{world}: references {relative}, which is neither beside it nor in {WORLDS}")
        target.parent.mkdir(parents=True, exist_ok=True)
        shutil.copyfile(source, target)
    atomic_write(out / SCENE_FILE, text)


def _image_is_done(path: Path, height: int, width: int) -> bool:
    from PIL import Image

    try:
        with Image.open(path) as im:
            return im.size == (width, height)
    except (OSError, ValueError):
        return False


RENDERERS = ("mitsuba", "cycles")


def generate(variant: str, out: str | Path, seed: int = 0, size: str = "full",
             resolution: tuple[int, int] | None = None, spp: int | None = None,
             progress: Callable[[int, int], None] | None = None, world: str | Path | None = None,
             renderer: str = "mitsuba", assets: str | Path | None = None) -> Path:
    """Render benchmark ``variant`` into folder ``out``; returns the labels file.

    ``world``: a Mitsuba XML to render instead of the variant's own (an edited copy of one; the
    variant still chooses the classes, poses and split sizes). Resumes a stopped run: images already
    on disk at the right resolution are kept. Refuses a folder that holds a different benchmark
    (other variant, seed, size, resolution or world). ``progress(done, total)`` is called after each
    image.

    ``renderer="cycles"`` renders with Blender Cycles from CLEVR's asset folder ``assets`` instead
    (:mod:`.cycles`; ``world`` is then a Cycles world JSON, default ``scenes/benchmarks/VARIANT.cycles.json``).
    """
    check_variant(variant)
    check_size(size)
    if renderer not in RENDERERS:
        raise BenchmarkError(f"unknown renderer {renderer!r}; choose one of {', '.join(RENDERERS)}")
    if renderer == "cycles":
        return _generate_cycles(variant, out, seed, size, resolution, spp, progress, world, assets)
    if assets is not None:
        raise BenchmarkError("--assets is for --renderer cycles; Mitsuba's worlds name their own files")
    from ..backend import mitsuba
    from ..images import write_png

    height, width = resolution or DEFAULT_RESOLUTION[size]
    out = Path(out)

    _check_out(out)
    shipped = world_file(variant)
    world = shipped if world is None else Path(world)
    if not world.is_file():
        raise BenchmarkError(f"{world}: no such world XML")
    defaults = read_defaults(world)
    spp = spp or (SMALL_SPP if size == "small" else int(defaults.get("spp", 128)))
    curve = defaults.get("tone_curve", "none")
    tone_map(np.zeros(1), curve)                                   # an unknown curve fails before any render
    if height < 8 or width < 8 or spp < 1:
        raise BenchmarkError(f"resolution {height}x{width} and spp {spp} are too small")
    images = plan(variant, seed, size)
    header = {"format": FORMAT, "version": FORMAT_VERSION, "variant": variant, "seed": seed, "size": size,
              "resolution": [height, width], "spp": spp, "scene": SCENE_FILE,
              **({} if world == shipped else {"world": world.name})}
    labels = {**header, "images": [label_of(im, image_overrides(im, defaults)[1]) for im in images]}

    world_text = _world_text(world, height, width, spp)
    _claim(out, labels, SCENE_FILE, world_text, world)
    _copy_world(world, out, world_text)
    atomic_write(out / LABELS_FILE, json.dumps(labels, indent=1))

    mi = mitsuba()

    def render(image, path: Path) -> None:
        overrides, _ = image_overrides(image, defaults)
        overrides.update(width=str(width), height=str(height), spp=str(spp))
        scene = mi.load_file(str(out / SCENE_FILE), parallel=False, **overrides)
        linear = np.asarray(mi.render(scene, seed=image.image_seed), dtype=np.float32)
        write_png(path, srgb_encode(tone_map(linear[..., :3], curve)))

    _render_missing(images, out, height, width, render, progress)
    return out / LABELS_FILE


def _check_out(out: Path) -> None:
    from ..files import refuse_inside_protected

    refuse_inside_protected(out, "mitsuba-p3 benchmark generate")   # out itself may be this benchmark, resumed
    if (out / "model.json").is_file():
        raise BenchmarkError(f"{out} is a fitted model; choose a new --out folder for the benchmark")


def _claim(out: Path, labels: dict, world_name: str, world_text: str, world: Path) -> None:
    """Start ``out`` as this benchmark's folder, or resume it: refused when it holds other labels or a world
    changed since it was started."""
    if (out / LABELS_FILE).is_file():
        _same_benchmark(out, labels)
        old = out / world_name
        if old.is_file() and old.read_text() != world_text:
            raise BenchmarkError(f"{world} has changed since {out} was started; finish it with the old world, "
                                 "or choose a new --out folder")
    out.mkdir(parents=True, exist_ok=True)


def _render_missing(images, out: Path, height: int, width: int, render: Callable, progress) -> None:
    """``render(image, path)`` every planned image not yet on disk at the right size, reporting progress."""
    todo = [im for im in images if not _image_is_done(out / im.file, height, width)]
    done = len(images) - len(todo)
    if progress:
        progress(done, len(images))
    for image in todo:
        render(image, out / image.file)
        done += 1
        if progress:
            progress(done, len(images))


def _same_benchmark(out: Path, labels: dict) -> None:
    """Refuse resuming into ``out`` unless its labels are exactly the ones this run would write."""
    try:
        existing = json.loads((out / LABELS_FILE).read_text())
    except (json.JSONDecodeError, UnicodeDecodeError):
        existing = None
    if existing != labels:
        raise BenchmarkError(f"{out} already holds a different benchmark (labels.json differs); "
                             "choose a new --out folder or delete it")


CYCLES_RESOLUTION = {"full": (240, 320), "small": (120, 160)}   # CLEVR's own image size for full
CYCLES_WORLD_FILE = "world.json"


def _generate_cycles(variant, out, seed, size, resolution, spp, progress, world, assets) -> Path:
    """:func:`generate` with Blender Cycles and CLEVR's assets (see :mod:`.cycles`)."""
    from dataclasses import replace

    from .cycles import CyclesRenderer, check_assets, load_world, world_file as cycles_world_file

    if variant == "ood":
        raise BenchmarkError("the Cycles renderer draws CLEVR's primitives; ood's objects are meshes: "
                             "use --renderer mitsuba for ood")
    height, width = resolution or CYCLES_RESOLUTION[size]
    if height < 8 or width < 8 or (spp is not None and spp < 1):
        raise BenchmarkError(f"resolution {height}x{width} and spp {spp} are too small")
    out = Path(out)
    _check_out(out)
    check_assets(assets)
    shipped = cycles_world_file(variant)
    world_path = shipped if world is None else Path(world)
    spec = load_world(world_path)
    spec = replace(spec, samples=spp or (SMALL_SPP if size == "small" else spec.samples))
    renderer = CyclesRenderer(assets, spec, height, width)
    images = plan(variant, seed, size)
    header = {"format": FORMAT, "version": FORMAT_VERSION, "variant": variant, "seed": seed, "size": size,
              "resolution": [height, width], "spp": spec.samples, "scene": CYCLES_WORLD_FILE,
              "renderer": "cycles", **({} if world is None else {"world": world_path.name})}
    labels = {**header, "images": [label_of(im, renderer.lamps(im)) for im in images]}
    world_text = json.dumps(spec.as_dict(), indent=1, default=str)
    _claim(out, labels, CYCLES_WORLD_FILE, world_text, world_path)
    atomic_write(out / CYCLES_WORLD_FILE, world_text)
    atomic_write(out / LABELS_FILE, json.dumps(labels, indent=1))
    _render_missing(images, out, height, width, renderer.render, progress)
    return out / LABELS_FILE
