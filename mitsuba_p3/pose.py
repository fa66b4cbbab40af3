"""Pose scores: ADI, the average distance for indistinguishable views (Hinterstoisser et al. 2012).

    ADI = mean over x in M_est of min over y in M_true ||x - y||

M_true is a set of surface points of the true shape, at its true size, in its
true pose (a KD-tree holds it); M_est is the same points moved to the estimated
pose (position x, y and yaw; the object rests on the floor, so its height is the
true one). The nearest-point distance makes the score blind to the symmetries
the image cannot resolve (a cube turned by 90 degrees scores 0). Primitives use
their analytic unit shapes; ood objects use their mesh.
"""
from __future__ import annotations

from functools import lru_cache

import numpy as np
from scipy.spatial import cKDTree

SURFACE_POINTS = 2000


@lru_cache(maxsize=32)
def unit_surface_points(shape: str, mesh: str | None = None, count: int = SURFACE_POINTS) -> np.ndarray:
    """(count, 3) points evenly spread over the object's unit-frame surface (seeded)."""
    import trimesh

    if mesh is not None:
        body = trimesh.load(mesh, force="mesh")
    elif shape == "sphere":
        body = trimesh.creation.icosphere(subdivisions=4, radius=1.0)
    elif shape == "cube":
        body = trimesh.creation.box(extents=(2.0, 2.0, 2.0))
    elif shape == "cylinder":
        body = trimesh.creation.cylinder(radius=1.0, height=2.0, sections=64)
    else:
        raise ValueError(f"no unit surface for shape {shape!r} without a mesh")
    points, _ = trimesh.sample.sample_surface(body, count, seed=0)
    return np.asarray(points, np.float64)


def true_surface(shot) -> np.ndarray:
    """World-space surface points of a labelled shot (:class:`mitsuba_p3.benchmarks.dataset.Shot`)."""
    unit = unit_surface_points(shot.cls.shape, str(shot.mesh) if shot.mesh is not None else None)
    m = np.asarray(shot.object_to_world, np.float64)
    return unit @ m[:3, :3].T + m[:3, 3]


def _yaw(angle: float) -> np.ndarray:
    c, s = np.cos(angle), np.sin(angle)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def adi(shot, shift: np.ndarray, yaw: float) -> float:
    """ADI (metres) of an estimated position (x, y) and yaw against the shot's true pose."""
    truth = true_surface(shot)
    centre = np.asarray(shot.position, np.float64)
    upright = (truth - centre) @ _yaw(-float(shot.yaw)).T        # the object at yaw 0, centred
    estimated = upright @ _yaw(float(yaw)).T + np.array([shift[0], shift[1], centre[2]])
    distances, _ = cKDTree(truth).query(estimated)
    return float(distances.mean())
