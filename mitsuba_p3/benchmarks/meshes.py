"""Ten everyday objects for the out-of-distribution benchmark, built with trimesh.

Each builder is deterministic. :func:`build_mesh` normalises a mesh to the
protocol's unit frame: centred on its bounding box, largest half-extent 1
(so the benchmark's uniform scale 0.035 gives a largest half-extent of 3.5 cm),
resting orientation with z up. ``scripts/make_scenes.py`` writes them to
``scenes/meshes/NAME.ply``; the benchmark XML loads those files.
"""
from __future__ import annotations

from functools import lru_cache
from pathlib import Path

import numpy as np
import trimesh

SECTIONS = 64  # segments around revolved shapes


def _revolve(profile) -> trimesh.Trimesh:
    """A solid of revolution about z from a (radius, height) polyline."""
    return trimesh.creation.revolve(np.asarray(profile, dtype=np.float64), sections=SECTIONS)


def _tube(path: np.ndarray, radius: float, sides: int = 16) -> trimesh.Trimesh:
    """A closed tube of circular cross-section along an open 3-D polyline (capped ends)."""
    tangents = np.gradient(path, axis=0)
    tangents /= np.linalg.norm(tangents, axis=1, keepdims=True)
    up = np.array([0.0, 1.0, 0.0])
    normal = np.cross(tangents, up)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    binormal = np.cross(tangents, normal)
    angles = np.linspace(0, 2 * np.pi, sides, endpoint=False)
    ring = (np.cos(angles)[None, :, None] * normal[:, None] + np.sin(angles)[None, :, None] * binormal[:, None])
    vertices = (path[:, None] + radius * ring).reshape(-1, 3)
    faces = []
    n = len(path)
    for i in range(n - 1):
        for j in range(sides):
            a, b = i * sides + j, i * sides + (j + 1) % sides
            c, d = a + sides, b + sides
            faces += [[a, b, d], [a, d, c]]
    centres = len(vertices)
    vertices = np.vstack([vertices, path[0], path[-1]])
    for j in range(sides):
        faces.append([centres, (j + 1) % sides, j])
        last = (n - 1) * sides
        faces.append([centres + 1, last + j, last + (j + 1) % sides])
    return trimesh.Trimesh(vertices, np.asarray(faces), process=True)


def mug() -> trimesh.Trimesh:
    body = _revolve([(0, 0), (0.8, 0), (0.8, 2.0), (0.7, 2.0), (0.7, 0.12), (0, 0.12)])
    t = np.linspace(-np.pi / 2, np.pi / 2, 24)
    handle_path = np.stack([0.75 + 0.55 * np.cos(t), np.zeros_like(t), 1.0 + 0.6 * np.sin(t)], axis=1)
    return trimesh.util.concatenate([body, _tube(handle_path, 0.1)])


def can() -> trimesh.Trimesh:
    return _revolve([(0, 0), (0.55, 0), (0.6, 0.08), (0.6, 1.92), (0.55, 2.0), (0.45, 2.0), (0.45, 1.96),
                     (0, 1.96)])


def bottle() -> trimesh.Trimesh:
    return _revolve([(0, 0), (0.5, 0), (0.5, 1.2), (0.42, 1.45), (0.2, 1.65), (0.17, 2.0), (0.19, 2.02),
                     (0.19, 2.12), (0, 2.12)])


def box() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(2.0, 1.4, 1.0))


def brick() -> trimesh.Trimesh:
    return trimesh.creation.box(extents=(2.0, 0.95, 0.6))


def bowl() -> trimesh.Trimesh:
    outer = [(1.0 * np.sin(a), 0.55 * (1 - np.cos(a)) + 0.05) for a in np.linspace(0.35, np.pi / 2, 12)]
    inner = [(0.9 * np.sin(a), 0.55 * (1 - np.cos(a)) + 0.12) for a in np.linspace(np.pi / 2, 0.0, 12)]
    return _revolve([(0, 0), (0.34, 0), (0.34, 0.05)] + outer + [(0.95, 0.62)] + inner)


def capsule() -> trimesh.Trimesh:
    """A pill bottle lying on its side."""
    mesh = trimesh.creation.capsule(height=1.4, radius=0.45, count=[SECTIONS, 32])
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [0, 1, 0]))
    return mesh


def cone() -> trimesh.Trimesh:
    return trimesh.creation.cone(radius=0.8, height=1.8, sections=SECTIONS)


def torus() -> trimesh.Trimesh:
    return trimesh.creation.torus(major_radius=0.7, minor_radius=0.28, major_sections=SECTIONS,
                                  minor_sections=24)


def bracket() -> trimesh.Trimesh:
    """An L-shaped bracket: an L profile in x-z extruded along y."""
    outline = np.array([(0, 0), (2.0, 0), (2.0, 0.3), (0.3, 0.3), (0.3, 1.5), (0, 1.5)], dtype=np.float64)
    triangles = np.array([[0, 1, 2], [0, 2, 3], [0, 3, 4], [0, 4, 5]])
    mesh = trimesh.creation.extrude_triangulation(outline, triangles, height=0.9)
    # extrude_triangulation extrudes along z: turn the L upright (profile in x-z, depth along y).
    mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))
    return mesh


BUILDERS = {"mug": mug, "can": can, "bottle": bottle, "box": box, "brick": brick, "bowl": bowl,
            "capsule": capsule, "cone": cone, "torus": torus, "bracket": bracket}
MESH_NAMES: tuple[str, ...] = tuple(BUILDERS)


@lru_cache(maxsize=None)
def build_mesh(name: str) -> trimesh.Trimesh:
    """The named object in the unit frame: bounding box centred at 0, largest half-extent 1."""
    if name not in BUILDERS:
        from ..errors import BenchmarkError

        raise BenchmarkError(f"unknown object {name!r}; choose one of {', '.join(MESH_NAMES)}")
    mesh = BUILDERS[name]()
    lo, hi = mesh.bounds
    mesh.apply_translation(-(lo + hi) / 2)
    mesh.apply_scale(2.0 / float(np.max(hi - lo)))
    return mesh


def mesh_half_extents(name: str) -> np.ndarray:
    """Half-extents of the unit-frame mesh (the largest is 1)."""
    lo, hi = build_mesh(name).bounds
    return (hi - lo) / 2


def write_meshes(folder: str | Path) -> list[Path]:
    """Write every object as ``folder/NAME.ply`` (binary PLY, vertices and faces only)."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for name in MESH_NAMES:
        path = folder / f"{name}.ply"
        path.write_bytes(trimesh.exchange.ply.export_ply(build_mesh(name), encoding="binary",
                                                          vertex_normal=False))
        paths.append(path)
    return paths
