"""Read and validate a benchmark folder in the project's documented format.

A data set is a folder holding ``labels.json``, the ``scene.xml`` its images
were made with (plus files that XML references), and PNG images in
``SPLIT/CLASS/SHOT.png``. The format is documented in the README ("Benchmark
data sets"). :func:`load_dataset` checks everything up front and reports
every problem at once; images are read lazily and resized to the inference
resolution.
"""
from __future__ import annotations

import json
from dataclasses import dataclass
from functools import cached_property
from pathlib import Path

import numpy as np

from ..errors import DatasetError
from ..images import ASPECT_TOLERANCE, INFERENCE_RESOLUTION, load_image
from ..scene import COLOURS, SIZES
from ..shapes import SHAPES
from .protocol import MATERIAL_NAMES, SPLITS, ClassLabel

FORMAT = "mitsuba-p3-benchmark"
FORMAT_VERSION = 1
LABELS_FILE = "labels.json"
SCENE_FILE = "scene.xml"
MAX_REPORTED = 12
# how far a labelled pose may disagree with itself: the object_to_world matrix against x, y, z, yaw and
# the half-extents (relative), and how far (metres) an object's lowest point may lie below the floor
MATRIX_TOLERANCE = 0.02
BELOW_FLOOR = 0.005



@dataclass(frozen=True)
class Shot:
    """One labelled image of a data set."""

    index: int
    file: Path
    split: str
    shot: int
    cls: ClassLabel
    position: np.ndarray        # (x, y, z) centre, metres
    yaw: float                  # radians about z
    scale: np.ndarray           # (3,) half-extents, metres
    object_to_world: np.ndarray  # (4, 4)
    mesh: Path | None           # ood: the mesh file (unit frame of object_to_world)

    @property
    def class_name(self) -> str:
        return self.cls.name


def _valid_rgb(rgb) -> bool:
    return isinstance(rgb, list) and len(rgb) == 3 and all(
        isinstance(v, int) and not isinstance(v, bool) and 0 <= v <= 255 for v in rgb)


def _class_from(record: dict) -> ClassLabel:
    c = record["class"]
    srgb = tuple(c["rgb"]) if _valid_rgb(c.get("rgb")) else None
    return ClassLabel(str(c["shape"]), str(c["colour"]), str(c["material"]), str(c["size"]), srgb)


def _check_class(where: str, record: dict, cls: ClassLabel, problems: list[str]) -> None:
    """What fit and evaluate will need of a class, checked before they start: a colour they can
    start from, a shape they can score."""
    rgb = record["class"].get("rgb")
    if rgb is not None and not _valid_rgb(rgb):
        problems.append(f"{where}: class rgb must be three whole numbers 0-255, got {rgb!r}")
    elif rgb is None and cls.colour not in COLOURS:
        problems.append(f"{where}: colour {cls.colour!r} is not one of CLEVR's ({', '.join(COLOURS)}); "
                        "give its sRGB as class.rgb, e.g. [255, 0, 255]")
    if cls.material not in MATERIAL_NAMES:
        problems.append(f"{where}: material {cls.material!r} is not one of {', '.join(MATERIAL_NAMES)} (the material "
                        "kinds fit learns and evaluate scores)")
    if cls.size not in SIZES:
        problems.append(f"{where}: size {cls.size!r} is not one of {', '.join(SIZES)}")
    if cls.shape not in SHAPES and not record.get("mesh"):
        problems.append(f"{where}: shape {cls.shape!r} is not a primitive ({', '.join(SHAPES)}); "
                        "give the object's mesh file as \"mesh\" (its pose error needs the surface)")


class Dataset:
    """A validated benchmark folder: its shots, classes and images at ``resolution``."""

    def __init__(self, root: Path, header: dict, shots: list[Shot], rgb: dict[str, tuple],
                 resolution: tuple[int, int]):
        self.root = root
        self.header = header
        self.shots = shots
        self.rgb = rgb
        self.resolution = resolution
        self._cache: dict[int, np.ndarray] = {}

    def __len__(self) -> int:
        return len(self.shots)

    def __repr__(self) -> str:
        counts = {s: len(self.classes(s)) for s in SPLITS}
        return (f"Dataset({self.root}, {len(self)} images, {counts['train']} train / "
                f"{counts['test']} test classes, resolution {self.resolution})")

    @property
    def variant(self) -> str:
        return str(self.header.get("variant", "custom"))

    @property
    def scene_file(self) -> Path:
        return self.root / self.header.get("scene", SCENE_FILE)

    def classes(self, split: str) -> list[str]:
        """Class names of a split, sorted."""
        return sorted({s.class_name for s in self.shots if s.split == split})

    def shots_of(self, class_name: str) -> list[Shot]:
        """A class's shots, ordered by shot index."""
        return sorted((s for s in self.shots if s.class_name == class_name), key=lambda s: s.shot)

    def split(self, split: str) -> list[Shot]:
        return [s for s in self.shots if s.split == split]

    @cached_property
    def class_labels(self) -> dict[str, ClassLabel]:
        return {s.class_name: s.cls for s in self.shots}

    def image(self, shot: Shot | int) -> np.ndarray:
        """The shot's image as float32 (H, W, 3) in [0, 1] at the data set's resolution."""
        index = shot if isinstance(shot, int) else shot.index
        if index not in self._cache:
            self._cache[index] = load_image(self.shots[index].file, self.resolution)
        return self._cache[index]


def _grouped(problems: list[str]) -> list[str]:
    """One line per kind of problem: ``a.png, b.png and 10 more: the problem`` (each problem reads
    ``WHERE: WHAT``), in the order first met."""
    groups: dict[str, list[str]] = {}
    for problem in problems:
        where, _, what = problem.partition(": ")
        groups.setdefault(what, []).append(where)
    lines = []
    for what, places in groups.items():
        more = f" and {len(places) - 2} more" if len(places) > 3 else ""
        lines.append(f"{', '.join(places[:2] if more else places)}{more}: {what}")
    return lines


def _inside(root: Path, relative) -> bool:
    """Whether a path from labels.json is relative and stays in the data-set folder (symbolic links
    followed): a data set never reads files elsewhere."""
    if not isinstance(relative, str) or Path(relative).is_absolute():
        return False
    base = Path(root).resolve()
    return (base / relative).resolve().is_relative_to(base)


def _number(value) -> float:
    """A label's number: an int or float (a string, a boolean or null is refused, not converted)."""
    if isinstance(value, bool) or not isinstance(value, (int, float)):
        raise TypeError(f"expected a number, got {value!r}")
    return float(value)


def _check_record(i: int, record: dict, root: Path, problems: list[str]) -> Shot | None:
    where = f"images[{i}]"
    try:
        file = root / record["file"]
        split = record["split"]
        if isinstance(record["shot"], bool) or not isinstance(record["shot"], int):
            raise TypeError(f"shot must be a whole number, got {record['shot']!r}")
        shot = record["shot"]
        cls = _class_from(record)
        pose = record["pose"]
        position = np.array([_number(pose[k]) for k in ("x", "y", "z")], dtype=np.float64)
        yaw = _number(pose["yaw"])
        scale = np.array([_number(v) for v in pose["scale"]], dtype=np.float64)
        matrix = np.array([[_number(v) for v in row] for row in pose["object_to_world"]], dtype=np.float64)
    except (KeyError, TypeError, ValueError) as exc:
        problems.append(f"{where}: missing or malformed field ({exc!r})")
        return None
    where = f"{record['file']}"
    _check_class(where, record, cls, problems)
    if split not in SPLITS:
        problems.append(f"{where}: split {split!r} is not one of {SPLITS}")
    if shot < 0:
        problems.append(f"{where}: shot must be 0 or more, got {shot}")
    if scale.shape != (3,) or np.any(~np.isfinite(scale)) or np.any(scale <= 0):
        problems.append(f"{where}: scale must be 3 positive half-extents, got {pose['scale']}")
    elif np.isfinite(position[2]) and position[2] - scale[2] < -BELOW_FLOOR:
        problems.append(f"{where}: the object's lowest point z - scale z = {position[2] - scale[2]:.3f} m lies below "
                        "the floor (z = 0)")
    if matrix.shape != (4, 4) or np.any(~np.isfinite(matrix)):
        problems.append(f"{where}: object_to_world must be a finite 4x4 matrix")
    else:
        _check_matrix(where, matrix, position, yaw, scale, bool(record.get("mesh")), problems)
    if not np.all(np.isfinite(position)) or not np.isfinite(yaw):
        problems.append(f"{where}: pose has non-finite values")
    if not _inside(root, record["file"]):
        problems.append(f"{where}: the image path must be relative and inside the data-set folder")
    elif not file.is_file():
        problems.append(f"{where}: image file is missing")
    mesh = record.get("mesh")
    mesh_path = root / mesh if mesh else None
    if mesh_path is not None and not _inside(root, mesh):
        problems.append(f"{where}: mesh {mesh} must be a relative path inside the data-set folder")
    elif mesh_path is not None and not mesh_path.is_file():
        problems.append(f"{where}: mesh {mesh} is missing")
    return Shot(i, file, split, shot, cls, position, yaw, scale, matrix, mesh_path)


def _check_matrix(where: str, matrix: np.ndarray, position: np.ndarray, yaw: float, scale: np.ndarray, mesh: bool,
                  problems: list[str]) -> None:
    """object_to_world against the pose's other fields: its translation is x, y, z; its linear part a
    turn by yaw about z times per-axis scales, which are the half-extents for a primitive (a mesh's are
    checked against its bounding box when the mesh is read: :func:`check_contents`)."""
    if not np.allclose(matrix[:3, 3], position, atol=1e-6):
        problems.append(f"{where}: object_to_world's translation {matrix[:3, 3].round(5).tolist()} "
                        f"disagrees with x, y, z {position.round(5).tolist()}")
    norms = np.linalg.norm(matrix[:3, :3], axis=0)
    c, s = np.cos(yaw), np.sin(yaw)
    turn = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    if np.any(norms <= 0) or not np.allclose(matrix[:3, :3] / np.where(norms > 0, norms, 1.0), turn,
                                             atol=MATRIX_TOLERANCE):
        problems.append(f"{where}: object_to_world's rotation is not a turn by yaw = {yaw:.4f} rad about z")
    elif not mesh and scale.shape == (3,) and np.any(np.abs(norms / scale - 1.0) > MATRIX_TOLERANCE):
        problems.append(f"{where}: object_to_world's scales {norms.round(5).tolist()} disagree with the half-extents "
                        f"{scale.round(5).tolist()}")


def check_contents(dataset: "Dataset") -> None:
    """Read every file a data set's labels name, as fit and evaluate will: each image through the
    loader inference uses (decoded, not only its header: transparency, bit depth and range are
    checked there), each mesh through trimesh, as the pose error reads it, its bounding box against
    the labelled half-extents. Raises :class:`DatasetError` listing every problem, as
    :func:`load_dataset` does; ``benchmark check`` calls it, so that "ready" means ready."""
    from ..errors import ImageError
    from ..pose import unit_surface_points

    problems: list[str] = []
    for shot in dataset.shots:
        try:
            load_image(shot.file, dataset.resolution)
        except ImageError as exc:
            problems.append(f"{shot.file.relative_to(dataset.root)}: {str(exc).partition(': ')[2] or exc}")
    meshes: dict[Path, np.ndarray | None] = {}
    for shot in dataset.shots:
        if shot.mesh is None:
            continue
        where = f"{shot.file.relative_to(dataset.root)}"
        if shot.mesh not in meshes:
            try:
                import trimesh

                body = trimesh.load(shot.mesh, force="mesh")
                if len(body.vertices) < 4 or len(body.faces) < 4 or not np.all(np.isfinite(body.vertices)):
                    raise ValueError("it has no surface")
                unit_surface_points(shot.cls.shape, str(shot.mesh))
                meshes[shot.mesh] = (body.bounds[1] - body.bounds[0]) / 2
            except Exception as exc:           # trimesh raises many types for a damaged file
                meshes[shot.mesh] = None
                problems.append(f"{where}: mesh {shot.mesh.name} cannot be read as a surface ({type(exc).__name__}: "
                                f"{exc})")
        bounds = meshes[shot.mesh]
        if bounds is not None:
            world = bounds * np.linalg.norm(shot.object_to_world[:3, :3], axis=0)
            if np.any(np.abs(world / shot.scale - 1.0) > MATRIX_TOLERANCE):
                problems.append(f"{where}: the mesh's half-extents in the world, {world.round(5).tolist()}, disagree "
                                f"with the labelled scale {shot.scale.round(5).tolist()}")
    if problems:
        raise DatasetError(_report(dataset.root, problems))


def _report(root: Path, problems: list[str]) -> str:
    lines = _grouped(problems)
    shown = "\n  ".join(lines[:MAX_REPORTED])
    more = f"\n  ... and {len(lines) - MAX_REPORTED} more" if len(lines) > MAX_REPORTED else ""
    return f"{root}: {len(problems)} problem(s) in the data set:\n  {shown}{more}"


def load_dataset(root: str | Path, resolution: tuple[int, int] = INFERENCE_RESOLUTION,
                 check_images: bool = True) -> Dataset:
    """Open and validate a data-set folder.

    Raises :class:`DatasetError` listing every missing or unreadable file and
    every inconsistent label. ``check_images`` also opens each image's header
    (fast) to find corrupt files and wrong aspects before a long run starts.
    """
    root = Path(root)
    labels_path = root / LABELS_FILE
    if not root.is_dir():
        raise DatasetError(f"{root}: no such data-set folder")
    if not labels_path.is_file():
        raise DatasetError(f"{root}: no {LABELS_FILE}; is this a benchmark folder? "
                           "(make one with `mitsuba-p3 benchmark generate`)")
    try:
        header = json.loads(labels_path.read_text())
    except json.JSONDecodeError as exc:
        raise DatasetError(f"{labels_path}: not valid JSON ({exc})") from None
    if not isinstance(header, dict) or header.get("format") != FORMAT:
        raise DatasetError(f"{labels_path}: \"format\" must be {FORMAT!r}")
    if header.get("version") != FORMAT_VERSION:
        raise DatasetError(f"{labels_path}: format version {header.get('version')!r} is not supported "
                           f"(this reader knows version {FORMAT_VERSION})")
    records = header.get("images")
    if not isinstance(records, list) or not records:
        raise DatasetError(f"{labels_path}: \"images\" must be a non-empty list")

    problems: list[str] = []
    shots = [s for i, r in enumerate(records) if (s := _check_record(i, r, root, problems)) is not None]
    # Consistency across images: one RGB, one split per class; unique shot indices.
    rgb: dict[str, tuple] = {}
    split_of: dict[str, str] = {}
    seen: set[tuple[str, int]] = set()
    files: dict[Path, Shot] = {}
    for shot, record in zip(shots, (records[s.index] for s in shots)):
        # one image per shot (a path outside the folder is reported above)
        same = files.setdefault(shot.file.resolve(), shot) if _inside(root, record["file"]) else shot
        if same is not shot:
            leak = " (a train/test leak)" if same.split != shot.split else ""
            problems.append(f"{record['file']}: the same image file as {records[same.index]['file']}{leak}: each "
                            "shot needs an image of its own")
        name = shot.class_name
        rgb_label = record["class"].get("rgb")
        colour = tuple(rgb_label) if _valid_rgb(rgb_label) else ()
        malformed = rgb_label is not None and not colour                    # reported above, once
        if not malformed and rgb.setdefault(name, colour) != colour:
            problems.append(f"{record['file']}: class {name} has RGB {list(colour)} here and "
                            f"{list(rgb[name])} elsewhere")
        if split_of.setdefault(name, shot.split) != shot.split:
            problems.append(f"{record['file']}: class {name} appears in both {split_of[name]} and {shot.split}")
        if (name, shot.shot) in seen:
            problems.append(f"{record['file']}: shot {shot.shot} of class {name} appears twice")
        seen.add((name, shot.shot))
    if check_images:
        from PIL import Image

        height, width = resolution
        for shot in shots:
            if not shot.file.is_file() or not _inside(root, str(records[shot.index]["file"])):
                continue                                      # reported above
            try:
                with Image.open(shot.file) as im:
                    im.verify()
                    w, h = im.size
            except Exception as exc:  # PIL raises many types for corrupt files
                problems.append(f"{shot.file.relative_to(root)}: unreadable image ({exc})")
                continue
            if abs((w / h) / (width / height) - 1.0) > ASPECT_TOLERANCE:
                problems.append(f"{shot.file.relative_to(root)}: aspect {w}x{h} does not match "
                                f"{width}x{height}")
    if problems:
        raise DatasetError(_report(root, problems))
    return Dataset(root, {k: v for k, v in header.items() if k != "images"}, shots, rgb, resolution)
