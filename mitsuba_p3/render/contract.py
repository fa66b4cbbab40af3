"""The one renderer contract: named parameter arrays in, float32 images out.

Every renderer (Mitsuba, the JAX tracer) takes the same flat mapping. Object
parameters may carry a leading batch dimension B (one image per row); global
parameters (lights, ambient light, floor) are shared by the whole batch.

========================  ==========  ==========================================
key                       shape       meaning
========================  ==========  ==========================================
shift                     (B,) 2      object position (x, y) on the floor, metres
theta                     (B,)        yaw about z, radians
scale                     (B,) 3      half-extents (x, y, z), metres, > 0
kappa                     (B,)        shape class: 0 sphere, 1 cube, 2 cylinder
colour                    (B,) 3      object albedo c
ambient, diffuse,         (B,)        k_a, k_d, k_s, alpha of the object
specular, shininess
light_position            K, 3        point-light positions, metres
light_intensity           K, 3        point-light RGB intensities
light_radius              ()          lights' radius, metres: soft shadows (0: point lights)
light_falloff             ()          distance d0, metres: intensities fall off as (d0 / d)^2
                                      (0: no falloff, the paper's lights)
sky, ground               3, 3        radiance of the environment's upper and lower hemisphere
                                      (the hemisphere term of :mod:`.hemisphere`; 0: point lights only)
ambient_light             3           A of the ambient term k_a c A
floor_colour              3           floor albedo, times floor_pattern
floor_ambient, ...        ()          floor k_a, k_d, k_s, alpha
floor_pattern             Ht, Wt, 3   floor pattern texture over the floor square
========================  ==========  ==========================================

Images are (H, W, 3), or (B, H, W, 3) when the object parameters are batched,
row 0 at the top, in [0, 1].
"""
from __future__ import annotations

from typing import Mapping

import numpy as np

from ..errors import SceneError

OBJECT_SHAPES: dict[str, tuple[int, ...]] = {
    "shift": (2,), "theta": (), "scale": (3,), "kappa": (), "colour": (3,),
    "ambient": (), "diffuse": (), "specular": (), "shininess": (),
}
GLOBAL_SHAPES: dict[str, tuple[int, ...] | None] = {
    "light_position": None, "light_intensity": None, "light_radius": (), "light_falloff": (),
    "sky": (3,), "ground": (3,),
    "ambient_light": (3,),
    "floor_colour": (3,), "floor_ambient": (), "floor_diffuse": (), "floor_specular": (),
    "floor_shininess": (), "floor_pattern": None,
}
KEYS = tuple(OBJECT_SHAPES) + tuple(GLOBAL_SHAPES)
FLOAT_KEYS = tuple(k for k in KEYS if k != "kappa")
# Parameters a renderer differentiates (geometry is sampled, not differentiated).
# (and the lights' radius, which acts through visibility alone, and their falloff distance, a fixed choice)
DIFFERENTIABLE_KEYS = tuple(k for k in FLOAT_KEYS
                            if k not in ("shift", "theta", "scale", "light_radius", "light_falloff"))


# Peak bytes per rendered pixel, about twice what was measured (`/usr/bin/time`, mitsuba-p3 render at
# 500x500 and 1500x1500: 49 bytes per added pixel); the material bases hold 12 channels, not 3.
BYTES_PER_PIXEL = {"image": 100, "bases": 300}


def memory_limit() -> float:
    """Bytes a render may take: ``MITSUBA_P3_MEMORY_GB`` if set, else 80% of the memory available now."""
    import os

    if os.environ.get("MITSUBA_P3_MEMORY_GB"):
        try:
            return float(os.environ["MITSUBA_P3_MEMORY_GB"]) * 2 ** 30
        except ValueError:
            raise SceneError(f"MITSUBA_P3_MEMORY_GB must be a number of gigabytes, got "
                             f"{os.environ['MITSUBA_P3_MEMORY_GB']!r}") from None
    try:
        with open("/proc/meminfo") as f:
            available = next(int(line.split()[1]) * 1024 for line in f if line.startswith("MemAvailable:"))
    except (OSError, StopIteration, ValueError):
        available = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES")
    return 0.8 * available


def check_memory(pixels: int, limit: float, kind: str = "image") -> None:
    """Refuse, before Dr.Jit allocates it, a render (batch x height x width ``pixels``) whose estimated
    memory exceeds ``limit`` bytes (:func:`memory_limit`)."""
    need = pixels * BYTES_PER_PIXEL[kind]
    if need > limit:
        raise SceneError(f"rendering {pixels:,} pixels ({kind}) needs about {need / 2 ** 30:.1f} GB, over the "
                         f"limit of {limit / 2 ** 30:.1f} GB; use a smaller resolution or batch, or set "
                         "MITSUBA_P3_MEMORY_GB")


def is_batched(params: Mapping[str, np.ndarray]) -> bool:
    """True when the object parameters carry a leading batch dimension."""
    return np.ndim(params["shift"]) == 2


def batch_size(params: Mapping[str, np.ndarray]) -> int:
    return int(np.shape(params["shift"])[0]) if is_batched(params) else 1


def check_params(params: Mapping[str, np.ndarray]) -> dict[str, np.ndarray]:
    """Validate a full parameter mapping and return float32/int32 copies.

    Unbatched object parameters are broadcast to the batch size when any object
    parameter is batched. Raises :class:`SceneError` naming the offending key.
    """
    missing = [k for k in KEYS if k not in params]
    if missing:
        raise SceneError(f"renderer parameters missing: {missing}")
    batch = None
    for key, base in OBJECT_SHAPES.items():
        shape = np.shape(params[key])
        if shape == base:
            continue
        if len(shape) == len(base) + 1 and shape[1:] == base:
            if batch is not None and shape[0] != batch:
                raise SceneError(f"parameter {key!r} has batch size {shape[0]}, others have {batch}")
            batch = shape[0]
            continue
        raise SceneError(f"parameter {key!r} must have shape {base} or (B, *{base}), got {shape}")
    out: dict[str, np.ndarray] = {}
    raw_kappa = np.asarray(params["kappa"])
    if raw_kappa.dtype.kind not in "iub" and not np.all(np.isfinite(raw_kappa) & (raw_kappa == np.round(raw_kappa))):
        raise SceneError(f"parameter 'kappa' is a class index and must be a whole number, got {raw_kappa.tolist()}")
    for key, base in OBJECT_SHAPES.items():
        dtype = np.int32 if key == "kappa" else np.float32
        value = np.asarray(params[key], dtype=dtype)
        if batch is not None and value.shape == base:
            value = np.broadcast_to(value, (batch, *base))
        out[key] = np.array(value, order="C")
    for key in GLOBAL_SHAPES:
        out[key] = np.array(params[key], dtype=np.float32, order="C")
    for key in FLOAT_KEYS:
        if not np.all(np.isfinite(out[key])):
            raise SceneError(f"parameter {key!r} has NaN or infinite values")
    if batch == 0:
        raise SceneError("the batch is empty")
    if np.any(out["scale"] <= 0):
        raise SceneError("parameter 'scale' must be positive half-extents")
    if np.any((out["kappa"] < 0) | (out["kappa"] > 2)):
        raise SceneError("parameter 'kappa' must be 0 (sphere), 1 (cube) or 2 (cylinder)")
    lp, li = out["light_position"], out["light_intensity"]
    if lp.ndim != 2 or lp.shape[1] != 3 or lp.shape[0] < 1 or li.shape != lp.shape:
        raise SceneError(f"light_position and light_intensity must both be (K, 3) with K >= 1, "
                         f"got {lp.shape} and {li.shape}")
    for key, base in GLOBAL_SHAPES.items():
        if base is not None and out[key].shape != base:
            raise SceneError(f"parameter {key!r} must have shape {base}, got {out[key].shape}")
    if np.any(out["sky"] < 0) or np.any(out["ground"] < 0):
        raise SceneError("sky and ground radiance must be >= 0")
    if out["light_radius"] < 0:
        raise SceneError(f"light_radius must be >= 0 metres, got {float(out['light_radius'])}")
    if not out["light_falloff"] >= 0:
        raise SceneError(f"light_falloff must be >= 0 metres, got {float(out['light_falloff'])}")
    pattern = out["floor_pattern"]
    if pattern.ndim != 3 or pattern.shape[2] != 3:
        raise SceneError(f"floor_pattern must be (H, W, 3), got {pattern.shape}")
    return out


def unbatch(params: Mapping[str, np.ndarray], index: int) -> dict[str, np.ndarray]:
    """Element ``index`` of a batched mapping, as an unbatched mapping."""
    return {k: (np.asarray(v)[index] if k in OBJECT_SHAPES else v) for k, v in params.items()}


class Renderer:
    """What every renderer shares: the scene, the resolution, and the parameter merge.

    Subclasses implement ``render(params)``, ``vjp(params, cotangent)`` and
    ``surface_ids(params)`` on numpy mappings.
    """

    name = "renderer"

    def __init__(self, scene, height: int | None = None, width: int | None = None, shadows: bool | None = None,
                 shadow_samples: int | None = None):
        from .soft_shadows import disc_pattern, samples_for

        scene.validate()
        self.scene = scene
        self.height = int(height or scene.camera.height)
        self.width = int(width or scene.camera.width)
        self.memory_limit = memory_limit()            # read once: renders are the samplers' hot path
        check_memory(self.height * self.width, self.memory_limit)   # one image's rays, before any is allocated
        self.shadows = scene.shadows if shadows is None else bool(shadows)
        self.floor_half_size = float(scene.floor.half_size)
        self.params = check_params(scene.params())  # the scene's values; render() overrides some
        # Points on each light's disc for the shadow rays (one: the centre, hard shadows); fixed at
        # construction, so a renderer made for a radius search passes shadow_samples explicitly.
        self.shadow_samples = samples_for(scene.light_radius, shadow_samples)
        self.shadow_pattern = disc_pattern(self.shadow_samples)
        # the hemisphere term is traced only for a world that has a sky or ground (render/hemisphere.py):
        # the paper's world pays nothing for it; fixed at construction, like the shadow samples
        self.environment = bool(np.any(self.params["sky"] > 0) or np.any(self.params["ground"] > 0))
        self.lobe = scene.lobe  # the specular lobe (render/lobes.py), fixed at construction
        # the lights' inverse-square falloff (render/falloff.py): traced only where the world
        # has one, so the paper's lights pay nothing for it; fixed at construction, like the lobe
        self.falloff = bool(self.params["light_falloff"] > 0)

    def merged(self, params: Mapping[str, np.ndarray] | None) -> dict[str, np.ndarray]:
        """The scene's parameters overridden by ``params``, checked."""
        merged = dict(self.params)
        if params:
            unknown = set(params) - set(merged)
            if unknown:
                raise SceneError(f"unknown renderer parameter(s) {sorted(unknown)}; known: {sorted(merged)}")
            merged.update(params)
        out = check_params(merged)
        if bool(out["light_falloff"] > 0) != self.falloff:
            # the falloff chooses the traced code at construction (as the lobe does): a call may change its
            # distance, not turn it on or off, which would otherwise be ignored or black out every light
            raise SceneError(f"light_falloff {float(out['light_falloff'])} in a call to a renderer made "
                             f"{'with' if self.falloff else 'without'} falloff: make the renderer from a scene "
                             "with the falloff wanted")
        return out

    def render_empty(self) -> np.ndarray:
        """The world without its object (shrunk to 10 micrometres, far below a pixel): the floor as the
        model predicts it, for the noise model's object/floor regions."""
        return self.render({"scale": np.full(3, 1e-5, np.float32)})
