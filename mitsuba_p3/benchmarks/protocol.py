"""The benchmark protocol of shared/BENCHMARK.md as code: classes, splits, poses.

A class is a tuple (shape, colour, material, size). :func:`plan` turns a
variant, a seed and a size into the full list of image labels -- which class,
split, shot and pose each image gets -- before anything is rendered, so a
generation can resume and two runs with one seed agree exactly. Classes and
poses depend on the seed only, not on the variant: ``fsclvr``, ``dark``, ``room``
and ``studio`` made with one seed show the same objects in the same poses.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from ..errors import BenchmarkError
from ..scene import COLOURS, SIZES
from ..shapes import SHAPES

VARIANTS: tuple[str, ...] = ("fsclvr", "dark", "room", "ood", "studio")
MATERIAL_NAMES: tuple[str, ...] = ("rubber", "metal")
SPLITS: tuple[str, ...] = ("train", "test")

# Pose: x, y ~ U(-POSE_RANGE, POSE_RANGE) (metres), yaw ~ U(-pi, pi).
POSE_RANGE = 0.08
# Out-of-distribution objects are scaled so their largest half-extent is this (metres).
OOD_HALF_EXTENT = 0.035



@dataclass(frozen=True)
class Size:
    """How many classes and shots a benchmark has."""

    train_classes: int
    test_classes: int
    shots: int


# Full sizes follow BENCHMARK.md; "small" is the built-in example for tests and the demo.
SIZES_BY_NAME: dict[str, dict[str, Size]] = {
    "full": {"fsclvr": Size(30, 20, 6), "dark": Size(30, 20, 6), "room": Size(30, 20, 6),
             "ood": Size(0, 10, 6), "studio": Size(30, 20, 6)},
    "small": {"fsclvr": Size(5, 5, 3), "dark": Size(5, 5, 3), "room": Size(5, 5, 3),
              "ood": Size(0, 5, 3), "studio": Size(5, 5, 3)},
}


@dataclass(frozen=True)
class ClassLabel:
    """One benchmark class; ``shape`` is a primitive or, for ood, an everyday object's name."""

    shape: str
    colour: str
    material: str
    size: str
    srgb: tuple | None = field(default=None, compare=False)   # the labels' own sRGB (0-255), if given

    @property
    def name(self) -> str:
        """Folder name, e.g. ``large-red-metal-cube``."""
        return f"{self.size}-{self.colour}-{self.material}-{self.shape}"

    @property
    def rgb(self) -> tuple[int, int, int]:
        """The colour's sRGB value, 0-255: the labels' own, else CLEVR's for its name."""
        return tuple(self.srgb) if self.srgb else COLOURS[self.colour]

    def as_dict(self) -> dict:
        return {"shape": self.shape, "colour": self.colour, "material": self.material, "size": self.size,
                "rgb": list(self.rgb)}


def all_classes() -> list[ClassLabel]:
    """The 96 primitive classes: 3 shapes x 8 colours x 2 materials x 2 sizes."""
    return [ClassLabel(shape, colour, material, size)
            for shape in SHAPES for colour in COLOURS for material in MATERIAL_NAMES for size in SIZES]


def check_variant(variant: str) -> str:
    if variant not in VARIANTS:
        raise BenchmarkError(f"unknown benchmark variant {variant!r}; choose one of {', '.join(VARIANTS)}")
    return variant


def check_size(size: str) -> str:
    if size not in SIZES_BY_NAME:
        raise BenchmarkError(f"unknown size {size!r}; choose one of {', '.join(SIZES_BY_NAME)}")
    return size


def draw_classes(variant: str, seed: int, size: str = "full") -> dict[str, list[ClassLabel]]:
    """Distinct classes for each split, drawn with ``seed``.

    Primitive variants draw train + test classes without replacement from the
    96; ``ood`` gives each everyday object (see :mod:`.meshes`) a colour and a
    material.
    """
    from .meshes import MESH_NAMES

    counts = SIZES_BY_NAME[check_size(size)][check_variant(variant)]
    if variant == "ood":
        rng = np.random.default_rng([seed, 1])
        names = list(MESH_NAMES[:counts.test_classes])
        colours = rng.choice(list(COLOURS), size=len(names))
        materials = rng.choice(MATERIAL_NAMES, size=len(names))
        test = [ClassLabel(n, str(c), str(m), "large") for n, c, m in zip(names, colours, materials)]
        return {"train": [], "test": test}
    classes = all_classes()
    rng = np.random.default_rng([seed, 0])  # the same stream for fsclvr, dark and room
    order = rng.permutation(len(classes))[:counts.train_classes + counts.test_classes]
    chosen = [classes[i] for i in order]
    return {"train": chosen[:counts.train_classes], "test": chosen[counts.train_classes:]}


@dataclass(frozen=True)
class Pose:
    """Ground-truth pose: centre (x, y, z), yaw about z (radians) and half-extents (metres)."""

    x: float
    y: float
    z: float
    yaw: float
    scale: tuple[float, float, float]

    def object_to_world(self, unit_scale: tuple[float, float, float] | None = None) -> np.ndarray:
        """4x4 matrix from the object's unit frame (centred, spanning [-1, 1] for primitives;
        the mesh file's own frame for meshes, with ``unit_scale`` its uniform scale) to world."""
        s = np.asarray(self.scale if unit_scale is None else unit_scale, dtype=np.float64)
        c, n = np.cos(self.yaw), np.sin(self.yaw)
        m = np.eye(4)
        m[:3, :3] = np.array([[c, -n, 0.0], [n, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(s)
        m[:3, 3] = (self.x, self.y, self.z)
        return m


def half_extents(cls: ClassLabel) -> tuple[float, float, float]:
    """The object's half-extents in metres (meshes: their bounding box at protocol size)."""
    if cls.shape in SHAPES:
        h = SIZES[cls.size]
        return (h, h, h)
    from .meshes import mesh_half_extents

    return tuple(float(v) * OOD_HALF_EXTENT for v in mesh_half_extents(cls.shape))


def draw_pose(rng: np.random.Generator, cls: ClassLabel) -> Pose:
    """A resting pose: uniform shift in the square, uniform yaw, centre height = half-extent z."""
    x, y = rng.uniform(-POSE_RANGE, POSE_RANGE, size=2)
    yaw = rng.uniform(-np.pi, np.pi)
    scale = half_extents(cls)
    return Pose(float(x), float(y), float(scale[2]), float(yaw), scale)


@dataclass(frozen=True)
class PlannedImage:
    """One image to render: where it goes and what it shows."""

    file: str
    split: str
    shot: int
    cls: ClassLabel
    pose: Pose
    image_seed: int


def plan(variant: str, seed: int, size: str = "full") -> list[PlannedImage]:
    """Every image's label, in render order, determined by (variant, seed, size) alone."""
    classes = draw_classes(variant, seed, size)
    shots = SIZES_BY_NAME[size][variant].shots
    rng = np.random.default_rng([seed, 2 if variant == "ood" else 0, 1])
    images = []
    for split in SPLITS:
        for cls in classes[split]:
            for shot in range(shots):
                pose = draw_pose(rng, cls)
                image_seed = int(rng.integers(0, 2**31 - 1))
                images.append(PlannedImage(f"{split}/{cls.name}/{shot}.png", split, shot, cls, pose,
                                           image_seed))
    return images
