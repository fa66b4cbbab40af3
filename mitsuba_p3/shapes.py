"""The primitive shapes: sphere, cube and closed cylinder.

Every shape lives in one *canonical object frame*: it spans [-1, 1] in x and y
and [0, 2] in z, so its base touches z = 0. An object with half-extents
``scale`` = (sx, sy, sz), yaw ``theta`` and ``shift`` = (x, y) therefore rests on
the floor under the transform ``translate(x, y, 0) . rotate_z(theta) . scale(s)``;
its centre is at height sz. One description of each shape (:data:`PARTS`) is
turned into Mitsuba dictionaries and XML, so the renderers and the scene files
cannot drift apart.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .errors import SceneError

SHAPES: tuple[str, ...] = ("sphere", "cube", "cylinder")


@dataclass(frozen=True)
class Part:
    """One analytic Mitsuba shape of a primitive, in the canonical object frame."""

    type: str
    props: dict = field(default_factory=dict)  # name -> 3-vector or float
    translate: tuple[float, float, float] = (0.0, 0.0, 0.0)
    scale: tuple[float, float, float] = (1.0, 1.0, 1.0)


# The cylinder is Mitsuba's open tube closed by two disks (the bottom one faces down).
PARTS: dict[str, tuple[Part, ...]] = {
    "sphere": (Part("sphere", {"center": (0.0, 0.0, 1.0), "radius": 1.0}),),
    "cube": (Part("cube", translate=(0.0, 0.0, 1.0)),),
    "cylinder": (
        Part("cylinder", {"p0": (0.0, 0.0, 0.0), "p1": (0.0, 0.0, 2.0), "radius": 1.0}),
        Part("disk", translate=(0.0, 0.0, 2.0)),
        Part("disk", scale=(1.0, 1.0, -1.0)),
    ),
}


def shape_index(name: str) -> int:
    """Class index kappa of a shape name (sphere 0, cube 1, cylinder 2)."""
    try:
        return SHAPES.index(name)
    except ValueError:
        raise SceneError(f"unknown shape {name!r}; choose one of {', '.join(SHAPES)}") from None


def part_to_world(part: Part, offset=(0.0, 0.0, 0.0)):
    """The Mitsuba ``to_world`` of a part, optionally moved by ``offset``."""
    from .backend import mitsuba

    mi = mitsuba()
    t = np.add(part.translate, offset)
    return mi.ScalarTransform4f().translate(t.tolist()).scale(list(part.scale))


def part_dict(part: Part, bsdf, offset=(0.0, 0.0, 0.0)) -> dict:
    """Mitsuba ``load_dict`` entry of a part, with the given BSDF (dict or object)."""
    entry = {"type": part.type, "bsdf": bsdf}
    if part.type in ("sphere", "cylinder"):
        # Analytic shapes keep their own centre/endpoints; move those, not to_world.
        for key, value in part.props.items():
            entry[key] = np.add(value, offset).tolist() if isinstance(value, tuple) else value
    else:
        entry["to_world"] = part_to_world(part, offset)
    return entry


def object_to_world(shift, theta: float, scale) -> np.ndarray:
    """4x4 matrix taking canonical object coordinates to world coordinates."""
    c, s = np.cos(theta), np.sin(theta)
    m = np.eye(4)
    m[:3, :3] = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]]) @ np.diag(scale)
    m[:2, 3] = shift
    return m
