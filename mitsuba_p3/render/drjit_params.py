"""The renderer contract's numpy parameters as Dr.Jit arrays, and gradients back to numpy.

Two traps shape this code: arrays built from numpy views keep numpy's buffer,
whose alignment Dr.Jit bakes into the kernel (a recompilation per render), and
width-1 arrays become literals in the kernel unless made opaque (a
recompilation per new value). Both are avoided here, once for every renderer.
"""
from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Mapping

import numpy as np

from ..backend import mitsuba
from .contract import FLOAT_KEYS, is_batched

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the backend has chosen libLLVM)


@dataclass
class DrParams:
    """The contract's parameters as Dr.Jit arrays (object fields have width B)."""

    shift: mi.Point2f
    theta: mi.Float
    scale: mi.Vector3f
    kappa: mi.UInt32
    colour: mi.Color3f
    ambient: mi.Float
    diffuse: mi.Float
    specular: mi.Float
    shininess: mi.Float
    light_position: mi.Point3f
    light_intensity: mi.Color3f
    light_radius: mi.Float
    light_falloff: mi.Float
    sky: mi.Color3f
    ground: mi.Color3f
    ambient_light: mi.Color3f
    floor_colour: mi.Color3f
    floor_ambient: mi.Float
    floor_diffuse: mi.Float
    floor_specular: mi.Float
    floor_shininess: mi.Float
    floor_pattern: mi.TensorXf
    batch: int = 1

    def differentiable(self) -> dict[str, object]:
        """The fields gradients can flow to (every float parameter)."""
        return {f.name: getattr(self, f.name) for f in fields(self) if f.name in FLOAT_KEYS}


def _vec(cls, array: np.ndarray):
    """(n, k) numpy -> a Dr.Jit k-vector of width n in Dr.Jit-owned memory.

    Built from lists on purpose: arrays made from numpy views keep numpy's buffer,
    whose alignment varies call to call, and Dr.Jit bakes the alignment into the
    kernel -- every render would then recompile.
    """
    array = np.asarray(array, np.float32)
    return cls(*[mi.Float(column.tolist()) for column in array.reshape(-1, array.shape[-1]).T])


def _scalars(array) -> mi.Float:
    return mi.Float(np.asarray(array, np.float32).reshape(-1).tolist())


def to_drjit_pattern(pattern: np.ndarray) -> mi.TensorXf:
    """The floor pattern as a tensor; Mitsuba bitmaps need >= 2x2 texels, so a 1-texel
    axis is repeated (bilinear lookups of a constant are unchanged)."""
    pattern = np.asarray(pattern, np.float32)
    if pattern.shape[0] < 2 or pattern.shape[1] < 2:
        pattern = np.repeat(np.repeat(pattern, 2 if pattern.shape[0] < 2 else 1, axis=0),
                            2 if pattern.shape[1] < 2 else 1, axis=1)
    return mi.TensorXf(pattern)


def to_drjit(params: Mapping[str, np.ndarray], pattern: mi.TensorXf | None = None) -> DrParams:
    """Convert a checked contract mapping (numpy) to :class:`DrParams`.

    ``pattern``, when given, is used as the floor pattern tensor instead of
    converting ``params["floor_pattern"]`` (the renderer reuses an uploaded one).
    """
    batch = params["shift"].shape[0] if is_batched(params) else 1
    scalar = lambda key: _scalars(params[key])  # noqa: E731
    p = DrParams(
        shift=_vec(mi.Point2f, np.asarray(params["shift"]).reshape(-1, 2)),
        theta=scalar("theta"),
        scale=_vec(mi.Vector3f, np.asarray(params["scale"]).reshape(-1, 3)),
        kappa=mi.UInt32(np.asarray(params["kappa"], np.uint32).reshape(-1).tolist()),
        colour=_vec(mi.Color3f, np.asarray(params["colour"]).reshape(-1, 3)),
        ambient=scalar("ambient"), diffuse=scalar("diffuse"),
        specular=scalar("specular"), shininess=scalar("shininess"),
        light_position=_vec(mi.Point3f, params["light_position"]),
        light_intensity=_vec(mi.Color3f, params["light_intensity"]),
        light_radius=scalar("light_radius"),
        light_falloff=scalar("light_falloff"),
        sky=_vec(mi.Color3f, np.asarray(params["sky"]).reshape(1, 3)),
        ground=_vec(mi.Color3f, np.asarray(params["ground"]).reshape(1, 3)),
        ambient_light=_vec(mi.Color3f, np.asarray(params["ambient_light"]).reshape(1, 3)),
        floor_colour=_vec(mi.Color3f, np.asarray(params["floor_colour"]).reshape(1, 3)),
        floor_ambient=scalar("floor_ambient"), floor_diffuse=scalar("floor_diffuse"),
        floor_specular=scalar("floor_specular"), floor_shininess=scalar("floor_shininess"),
        floor_pattern=pattern if pattern is not None else to_drjit_pattern(params["floor_pattern"]),
        batch=batch,
    )
    # Width-1 arrays would otherwise be baked into the kernel as literals: a new value
    # would recompile it. Opaque values keep one kernel for all parameter values.
    for f in fields(p):
        value = getattr(p, f.name)
        if f.name != "batch":
            dr.make_opaque(value)
    return p


def gradients_of(targets: Mapping[str, object], merged: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Numpy gradients of the Dr.Jit ``targets``, shaped like the contract's arrays."""
    grads = {}
    for key, value in targets.items():
        g = dr.grad(value)
        array = g.numpy() if isinstance(g, mi.TensorXf) else np.asarray(g).T
        grads[key] = np.asarray(array, np.float32).reshape(np.shape(merged[key]))
    return grads
