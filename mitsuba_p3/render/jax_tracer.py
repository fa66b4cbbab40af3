"""A native JAX ray tracer of the same scenes, behind the same contract.

It shares no rendering code with the Mitsuba renderer, only the scene
description and the contract, so the two check each other. It intersects the
analytic shapes in the canonical object frame (see :mod:`mitsuba_p3.shapes`):
a sphere (an ellipsoid after scaling), a box and a capped cylinder, each under
shift, yaw and scale. The floor z = 0 carries a bilinear pattern texture. The
same Phong model and point lights are used, with optional shadows (hard, or soft
from lights widened into discs: :mod:`.soft_shadows`) and rays
through pixel centres.

Specialised rather than switched: each shape class has its own traced function,
so nothing evaluates the other shapes' intersections. A single render calls the
jitted function of its class. How a batch runs follows the device
(:func:`batching_for`): on a CPU, ``lax.map`` over elements with a ``lax.switch``
on the class, which executes only the branch taken, one image after another; on
a GPU, ``vmap``, which turns the switch into a select of all three branches but
fills the device's width (the whole batch is one launch; the paper found vmapped
batches slower than single frames, on a CPU). ``MITSUBA_P3_JAX_BATCHING`` forces
``map`` or ``vmap``.

Everything is float32, jit-compiled and differentiable with ``jax.grad`` for
colour, material, light and floor parameters. Geometry is under
``stop_gradient``, as in the Mitsuba renderer.
"""
from __future__ import annotations

from functools import partial
from typing import Mapping

import jax
import jax.numpy as jnp
import numpy as np

from ..scene import Camera, Scene
from ..shapes import SHAPES
from . import hemisphere
from .falloff import falloff
from .lobes import ggx_term, sharpness
from .contract import OBJECT_SHAPES, Renderer, is_batched, unbatch

BATCHINGS = ("map", "vmap")
BATCHING_ENV = "MITSUBA_P3_JAX_BATCHING"
SHADOW_OFFSET = 1e-4  # metres along the normal for shadow rays (as the Mitsuba renderer)
_TINY = 1e-30
_EPS = 1e-6  # canonical units: hits closer than this to a ray's origin are ignored


def batching_for(platform: str | None = None) -> str:
    """How a batch of renders runs: ``vmap`` on a GPU (one wide launch), ``map`` elsewhere
    (one image at a time, each class's branch alone); ``MITSUBA_P3_JAX_BATCHING`` forces either."""
    from ..backend import follow_device
    from ..errors import SceneError

    return follow_device(BATCHING_ENV, BATCHINGS, "vmap", "map", SceneError, platform)


def camera_frame(camera: Camera, height: int, width: int) -> tuple:
    """The pinhole camera's origin, forward, left and up unit vectors (3,) and the tangents of its half
    fields of view (x, y) for a ``height`` x ``width`` image: the image's left edge lies towards
    ``cross(up, forward)`` and its top towards the camera's up vector (Mitsuba's perspective camera
    convention)."""
    origin = np.asarray(camera.origin, np.float64)
    forward = np.asarray(camera.target, np.float64) - origin
    forward /= np.linalg.norm(forward)
    left = np.cross(camera.up, forward)
    left /= np.linalg.norm(left)
    tan_y = np.tan(np.radians(camera.fov) / 2)
    return origin, forward, left, np.cross(forward, left), tan_y * width / height, tan_y


def camera_rays(camera: Camera, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
    """Pinhole rays through pixel centres: origin (3,) and unit directions (H*W, 3), row-major
    (:func:`camera_frame`'s convention)."""
    origin, forward, left, up, tan_x, tan_y = camera_frame(camera, height, width)
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    uu, vv = np.meshgrid(u, v)
    d = (forward[None, None] + ((1 - 2 * uu) * tan_x)[..., None] * left
         + ((1 - 2 * vv) * tan_y)[..., None] * up)
    d /= np.linalg.norm(d, axis=-1, keepdims=True)
    return origin.astype(np.float32), d.reshape(-1, 3).astype(np.float32)


# ---------------------------------------------------------------- intersection (canonical frame)
# Vectors are (3, N) arrays (structure of arrays: XLA vectorises along N). Each
# intersection returns (t, normal) for rays o + t d (d not normalised); t = inf where missed.

def _dot(a, b):
    return a[0] * b[0] + a[1] * b[1] + a[2] * b[2]


def _sphere(o, d):
    """Unit sphere centred at (0, 0, 1); the closest-approach form keeps float32 precise."""
    oc = o - jnp.array([0.0, 0.0, 1.0])[:, None]
    a = _dot(d, d)
    t_mid = -_dot(oc, d) / a
    closest = oc + t_mid * d
    r2 = _dot(closest, closest)
    half = jnp.sqrt(jnp.maximum((1.0 - r2) / a, 0.0))
    t_near, t_far = t_mid - half, t_mid + half
    t = jnp.where(t_near > _EPS, t_near, jnp.where(t_far > _EPS, t_far, jnp.inf))
    t = jnp.where(r2 <= 1.0, t, jnp.inf)
    return t, oc + t * d


def _box(o, d):
    """The box [-1, 1]^2 x [0, 2] by slabs; the normal is the face the ray enters (or leaves)."""
    lo = jnp.array([-1.0, -1.0, 0.0])[:, None]
    hi = jnp.array([1.0, 1.0, 2.0])[:, None]
    safe = jnp.where(jnp.abs(d) > 1e-12, d, 1e-12)
    t_a, t_b = (lo - o) / safe, (hi - o) / safe
    t_min, t_max = jnp.minimum(t_a, t_b), jnp.maximum(t_a, t_b)
    t_in = jnp.maximum(jnp.maximum(t_min[0], t_min[1]), t_min[2])
    t_out = jnp.minimum(jnp.minimum(t_max[0], t_max[1]), t_max[2])
    enter = t_in > _EPS
    hit = t_out >= jnp.maximum(t_in, 0.0)
    t = jnp.where(hit, jnp.where(enter, t_in, jnp.where(t_out > _EPS, t_out, jnp.inf)), jnp.inf)
    face = jnp.where(enter, t_in, t_out)
    crossing = jnp.where(enter, t_min, t_max)
    sign = jnp.where(enter, -jnp.sign(safe), jnp.sign(safe))
    return t, jnp.where(crossing == face, sign, 0.0)


def _cylinder(o, d):
    """x^2 + y^2 <= 1, 0 <= z <= 2: the side (closest-approach quadratic) and both caps."""
    a = d[0] * d[0] + d[1] * d[1]
    a_safe = jnp.where(a > 1e-20, a, 1.0)
    t_mid = -(o[0] * d[0] + o[1] * d[1]) / a_safe
    cx, cy = o[0] + t_mid * d[0], o[1] + t_mid * d[1]
    r2 = cx * cx + cy * cy
    half = jnp.sqrt(jnp.maximum((1.0 - r2) / a_safe, 0.0))
    side_ok = (a > 1e-20) & (r2 <= 1.0)
    # Keep the nearest candidate and which part it is (0 side, 1 top cap, -1 bottom cap);
    # the normal is built once at the end.
    best_t = jnp.full_like(a, jnp.inf)
    part = jnp.zeros_like(a)
    for t_side in (t_mid - half, t_mid + half):
        z = o[2] + t_side * d[2]
        ok = side_ok & (t_side > _EPS) & (z >= 0.0) & (z <= 2.0) & (t_side < best_t)
        best_t = jnp.where(ok, t_side, best_t)
    dz_safe = jnp.where(jnp.abs(d[2]) > 1e-12, d[2], 1e-12)
    for height, code in ((2.0, 1.0), (0.0, -1.0)):
        t_cap = (height - o[2]) / dz_safe
        px, py = o[0] + t_cap * d[0], o[1] + t_cap * d[1]
        ok = (t_cap > _EPS) & (px * px + py * py <= 1.0) & (t_cap < best_t)
        best_t = jnp.where(ok, t_cap, best_t)
        part = jnp.where(ok, code, part)
    side = part == 0.0
    normal = jnp.stack([jnp.where(side, o[0] + best_t * d[0], 0.0), jnp.where(side, o[1] + best_t * d[1], 0.0),
                        part])
    return best_t, normal


INTERSECT = {"sphere": _sphere, "cube": _box, "cylinder": _cylinder}


# ---------------------------------------------------------------- shading

def _yaw(cos_t, sin_t, v):
    return jnp.stack([cos_t * v[0] - sin_t * v[1], sin_t * v[0] + cos_t * v[1], v[2]])


def _object_hit(intersect, p, origin, direction):
    """World rays (3, N) against the object: (world t, world unit normal)."""
    cos_t, sin_t = jnp.cos(p["theta"]), jnp.sin(p["theta"])
    shift = jnp.concatenate([p["shift"], jnp.zeros(1, origin.dtype)])[:, None]
    scale = p["scale"][:, None]
    o = _yaw(cos_t, -sin_t, origin - shift) / scale
    d = _yaw(cos_t, -sin_t, direction) / scale
    t, n = intersect(o, d)
    n = _yaw(cos_t, sin_t, n / scale)
    return t, n * jax.lax.rsqrt(jnp.maximum(_dot(n, n), _TINY))


def bilinear(texture, u, v):
    """Bilinear lookup (3, N) with texel centres at (i + 0.5) / size, v = 0 at row 0, clamped edges."""
    rows, cols = texture.shape[0], texture.shape[1]
    x = u * cols - 0.5
    y = v * rows - 0.5
    x0, y0 = jnp.floor(x), jnp.floor(y)
    fx, fy = x - x0, y - y0
    xa = jnp.clip(x0.astype(jnp.int32), 0, cols - 1)
    xb = jnp.clip(x0.astype(jnp.int32) + 1, 0, cols - 1)
    ya = jnp.clip(y0.astype(jnp.int32), 0, rows - 1)
    yb = jnp.clip(y0.astype(jnp.int32) + 1, 0, rows - 1)
    top = texture[ya, xa].T * (1 - fx) + texture[ya, xb].T * fx
    bottom = texture[yb, xa].T * (1 - fx) + texture[yb, xb].T * fx
    return top * (1 - fy) + bottom * fy


def highlight(shininess, cos_reflect):
    """The Phong highlight max(0, r.v)^alpha (safe for alpha near 0 and r.v near 0; alpha < 0 reads as 0)."""
    return jnp.where(cos_reflect > 0, jnp.exp(sharpness(shininess) * jnp.log(jnp.maximum(cos_reflect, _TINY))), 0.0)


def _geometry(intersect, p, origin, directions, floor_half_size: float):
    """First hits: (hit_object, hit_floor, point, normal, floor_point), all finite."""
    t_obj, n_obj = _object_hit(intersect, p, origin, directions)
    t_floor = -origin[2] / directions[2]
    floor_point = origin + t_floor * directions
    h = floor_half_size
    hit_floor = (directions[2] < 0) & (t_floor > 0) & (jnp.abs(floor_point[0]) <= h) & (
        jnp.abs(floor_point[1]) <= h)
    hit_obj = jnp.isfinite(t_obj) & (~hit_floor | (t_obj < t_floor))
    hit_floor = hit_floor & ~hit_obj
    t = jnp.where(hit_obj, t_obj, jnp.where(hit_floor, t_floor, 0.0))
    point = origin + t * directions
    normal = jnp.where(hit_obj, n_obj, jnp.array([0.0, 0.0, 1.0])[:, None])
    floor_point = jnp.where(hit_floor, floor_point, 0.0)
    return hit_obj, hit_floor, point, normal, floor_point


def silhouette(p: Mapping[str, jnp.ndarray], origin, directions, floor_half_size: float):
    """(N,) whether each camera ray (directions (N, 3), from ``origin`` (3,)) sees the object first, for one
    object (``shift``, ``theta``, ``scale`` and a class index ``kappa`` into :data:`SHAPES`, which may be
    traced): the object's pixels without shading it. Under ``vmap`` over a traced class every class's
    intersection is computed and one kept (three cheap ray tests per ray)."""
    pose = {k: p[k] for k in ("shift", "theta", "scale")}
    origin, directions = jnp.asarray(origin)[:, None], jnp.asarray(directions).T

    def covered(intersect):
        return _geometry(intersect, pose, origin, directions, floor_half_size)[0]

    return jax.lax.stop_gradient(jax.lax.switch(
        jnp.asarray(p["kappa"], jnp.int32), [partial(covered, INTERSECT[shape]) for shape in SHAPES]))


def surface_normals(p: Mapping[str, jnp.ndarray], origin, directions, floor_half_size: float):
    """(N, 3) the world unit normal of the object where each camera ray sees it first, (0, 0, 1) elsewhere:
    :func:`silhouette`'s geometry with the normals it finds (the shading fields on the object's normals,
    :mod:`mitsuba_p3.fit.irradiance`)."""
    pose = {k: p[k] for k in ("shift", "theta", "scale")}
    origin, directions = jnp.asarray(origin)[:, None], jnp.asarray(directions).T

    def normals(intersect):
        return _geometry(intersect, pose, origin, directions, floor_half_size)[3].T

    return jax.lax.stop_gradient(jax.lax.switch(
        jnp.asarray(p["kappa"], jnp.int32), [partial(normals, INTERSECT[shape]) for shape in SHAPES]))


def _materialised(fn, predicate):
    """``fn()``, computed once into buffers.

    XLA CPU fuses (and so repeats) cheap producers into every consumer, and it expands
    ``optimization_barrier`` before fusing; a conditional is a real boundary. Without
    it the geometry was recomputed inside each light's loop. ``predicate`` is always true; the other branch returns zeros.
    """
    return jax.lax.cond(predicate, fn, lambda: jax.tree_util.tree_map(jnp.zeros_like, jax.eval_shape(fn)))


def _visibility(intersect, pose, point, normal, to_light, distance, centre, radius, pattern):
    """The share of a light's disc reached by shadow rays from just above ``point`` (N,): the
    disc has radius ``radius`` about ``centre`` and faces the point; ``pattern`` (n, 2) are its
    sample points in the unit disc (one: the centre, i.e. a hard shadow along ``to_light``)."""
    start = point + normal * SHADOW_OFFSET
    if pattern is None or len(pattern) == 1:
        t_block, _ = _object_hit(intersect, pose, start, to_light)
        return (t_block >= distance).astype(point.dtype)
    axis = centre - start
    axis = axis * jax.lax.rsqrt(_dot(axis, axis))
    # Duff et al.'s orthonormal basis about the axis (as the Mitsuba renderer)
    sign = jnp.where(axis[2] >= 0, 1.0, -1.0)
    a = -1.0 / (sign + axis[2])
    b = axis[0] * axis[1] * a
    first = jnp.stack([1.0 + sign * axis[0] * axis[0] * a, sign * b, -sign * axis[0]])
    second = jnp.stack([b, sign + axis[1] * axis[1] * a, -axis[1]])
    visible = jnp.zeros_like(distance)
    for x, y in np.asarray(pattern).tolist():
        ray = centre + radius * (x * first + y * second) - start
        length = jnp.sqrt(_dot(ray, ray))
        t_block, _ = _object_hit(intersect, pose, start, ray / length)
        visible = visible + (t_block >= length).astype(point.dtype) / len(pattern)
    return visible


def trace(shape: str, p: Mapping[str, jnp.ndarray], origin, directions, floor_half_size: float,
          shadows: bool, ids: bool = False, bases: bool = False, shadow_pattern=None, environment: bool = True,
          lobe: str = "phong", falloff_on: bool = False):
    """Render one parameter set of a shape class from rays (3, N).

    Returns (N, 3) colours, or (N,) surface ids, or with ``bases`` the (N, 4, 3)
    material bases of :meth:`JaxRenderer.render_bases`.
    """
    intersect = INTERSECT[shape]
    origin = origin[:, None]
    pose = jax.lax.stop_gradient({k: p[k] for k in ("shift", "theta", "scale")})
    hit_obj, hit_floor, point, normal, floor_point = jax.lax.stop_gradient(
        _materialised(partial(_geometry, intersect, pose, origin, directions, floor_half_size),
                      jnp.all(pose["scale"] > 0)))
    if ids:
        return jnp.where(hit_obj, 2, jnp.where(hit_floor, 1, 0))
    view = -directions
    h = floor_half_size

    floor_albedo = p["floor_colour"][:, None] * bilinear(p["floor_pattern"], (floor_point[0] / h + 1) * 0.5,
                                                         (floor_point[1] / h + 1) * 0.5)
    pick = lambda obj, floor: jnp.where(hit_obj, obj, floor)  # noqa: E731
    albedo = pick(p["colour"][:, None], floor_albedo)
    ambient = pick(p["ambient"], p["floor_ambient"])
    diffuse = pick(p["diffuse"], p["floor_diffuse"])
    specular = pick(p["specular"], p["floor_specular"])
    shininess = pick(p["shininess"], p["floor_shininess"])

    # The Phong sum, per light: I_l [n.l > 0] (k_d c n.l + k_s max(0, r.v)^alpha). Its two
    # light sums D = sum I_l [n.l > 0] n.l and S = sum I_l [n.l > 0] max(0, r.v)^alpha
    # make the image affine in the materials: k_a c A + k_d c D + k_s S.
    lit_diffuse = jnp.zeros_like(point)
    lit_specular = jnp.zeros_like(point)
    for k in range(p["light_position"].shape[0]):
        to_light = p["light_position"][k][:, None] - point
        distance = jnp.sqrt(_dot(to_light, to_light))
        l = to_light / distance
        cos_light = _dot(normal, l)
        reflected = 2 * cos_light * normal - l
        lit = cos_light > 0
        visible = 1.0
        if shadows:
            visible = jax.lax.stop_gradient(_visibility(
                intersect, pose, point, normal, l, distance, p["light_position"][k][:, None],
                p["light_radius"], shadow_pattern))
        intensity = p["light_intensity"][k][:, None]
        if falloff_on:   # inverse-square falloff about the reference distance (render/falloff.py)
            intensity = intensity * falloff(p["light_falloff"], distance)
        lit_diffuse = lit_diffuse + jnp.where(lit, visible * intensity * cos_light, 0.0)
        if lobe == "ggx":
            half = l + view
            half = half / jnp.sqrt(jnp.maximum(_dot(half, half), 1e-12))
            specular_term = ggx_term(shininess, jnp.maximum(cos_light, 0.0), jnp.maximum(_dot(normal, view), 0.0),
                                     _dot(normal, half), jnp.sqrt)
        else:
            specular_term = highlight(shininess, _dot(reflected, view))
        lit_specular = lit_specular + jnp.where(lit, visible * intensity * specular_term, 0.0)
    # the environment as two hemispheres (render/hemisphere.py): zero unless the world has a sky or ground
    if environment:
        sky, ground = p["sky"][:, None], p["ground"][:, None]
        lit_diffuse = lit_diffuse + hemisphere.diffuse_term(normal[2], sky, ground)
        reflected_z = 2 * _dot(normal, view) * normal[2] - view[2]
        lit_specular = lit_specular + hemisphere.specular_term(reflected_z, shininess, sky, ground, jnp.arcsin,
                                                               jax.lax.erf, jnp.sqrt, jnp.clip)
    ambient_light = p["ambient_light"][:, None]
    result = ambient * albedo * ambient_light + diffuse * albedo * lit_diffuse + specular * lit_specular
    valid = hit_obj | hit_floor
    image = jnp.where(valid, jnp.clip(result, 0.0, 1.0), 0.0)
    if not bases:
        return image.T
    on_object = lambda v: jnp.where(hit_obj, v, 0.0)  # noqa: E731
    ambient_basis = on_object(jnp.broadcast_to(ambient_light, point.shape))
    return jnp.stack([ambient_basis, on_object(lit_diffuse), on_object(lit_specular),
                      jnp.where(hit_obj, 0.0, image)]).transpose(2, 0, 1)


class JaxRenderer(Renderer):
    """Render the one-object Phong scene contract with the JAX tracer.

    Same interface as :class:`~mitsuba_p3.render.mitsuba.MitsubaRenderer`:
    :meth:`render`, :meth:`vjp` and :meth:`surface_ids` on numpy mappings, plus
    :meth:`render_jax`, a pure function of a mapping of JAX arrays (jit- and
    grad-able) for use inside JAX programs.
    """

    name = "jax"

    def __init__(self, scene: Scene, height: int | None = None, width: int | None = None,
                 shadows: bool | None = None, shadow_samples: int | None = None):
        super().__init__(scene, height, width, shadows, shadow_samples)
        self.batching = batching_for()
        origin, directions = camera_rays(scene.camera, self.height, self.width)
        self._origin, self._directions = jnp.asarray(origin), jnp.asarray(directions.T)  # (3, N)
        self._single = {
            shape: jax.jit(partial(self._trace_shape, shape)) for shape in SHAPES
        }
        self._batched = jax.jit(self._trace_batch)
        self._single_bases = {shape: jax.jit(partial(self._trace_shape, shape, bases=True)) for shape in SHAPES}
        self._batched_bases = jax.jit(partial(self._trace_batch, bases=True))
        self._ids = {shape: jax.jit(partial(self._trace_shape, shape, ids=True)) for shape in SHAPES}
        self._vjps: dict = {}  # jitted pullbacks, per render function

    # ------------------------------------------------------------------ pure JAX
    def _window_rays(self, window):
        """The camera rays (3, h*w) of a window ``((top, left), (h, w))``: the offset may be traced (one
        compiled function serves every window of that size), the size is static. None: every pixel."""
        if window is None:
            return self._directions, (self.height, self.width)
        offset, (height, width) = window
        grid = self._directions.reshape(3, self.height, self.width)
        top, left = offset[0], offset[1]
        rays = jax.lax.dynamic_slice(grid, (0, top, left), (3, height, width))
        return rays.reshape(3, height * width), (height, width)

    def _trace_shape(self, shape: str, p, ids: bool = False, bases: bool = False, window=None):
        directions, (height, width) = self._window_rays(window)
        out = trace(shape, p, self._origin, directions, self.floor_half_size, self.shadows, ids, bases,
                    self.shadow_pattern, self.environment, self.lobe, self.falloff)
        return out.reshape(height, width, *(() if ids else (4, 3) if bases else (3,)))

    def _trace_batch(self, p, bases: bool = False, window=None):
        objects = {k: p[k] for k in OBJECT_SHAPES}
        shared = {k: v for k, v in p.items() if k not in objects}
        branches = [partial(lambda shape, obj: self._trace_shape(shape, {**shared, **obj}, bases=bases,
                                                                 window=window), shape)
                    for shape in SHAPES]
        one = lambda obj: jax.lax.switch(obj["kappa"], branches, obj)  # noqa: E731
        return jax.vmap(one)(objects) if self.batching == "vmap" else jax.lax.map(one, objects)

    def render_jax(self, p: Mapping[str, jnp.ndarray], bases: bool = False, window=None) -> jnp.ndarray:
        """Pure JAX render of a full parameter mapping (batched or not); kappa may be traced.

        With ``bases``, the material bases of :meth:`render_bases` instead of the image. With ``window``
        ``((top, left), (height, width))`` only that window's pixels are traced (exactly that crop of
        the whole image; the offset may be traced, the size is static), as the Mitsuba renderer's
        :meth:`~mitsuba_p3.render.mitsuba.MitsubaRenderer.window` does."""
        if p["shift"].ndim == 2:
            return self._trace_batch(p, bases, window)
        return self._trace_batch({k: (v[None] if k in OBJECT_SHAPES else v) for k, v in p.items()}, bases,
                                 window)[0]

    def render_bases(self, params: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """The image's material bases, (H, W, 4, 3) or (B, H, W, 4, 3): A, D, S and F.

        On the object's pixels the image is ``clip(c (k_a A + k_d D) + k_s S)``: A is the
        ambient light, D and S the light sums of the Phong diffuse and specular terms.
        F is the image elsewhere (and 0 on the object). The object's materials enter
        only through these formulas, so one render serves any colour and weights at
        this pose, class and shininess (:meth:`PosteriorModel.material_move`)."""
        merged = self.merged(params)
        if not is_batched(merged):
            return np.asarray(self._single_bases[SHAPES[int(merged["kappa"])]](merged))
        return np.asarray(self._batched_bases(merged))

    # ------------------------------------------------------------------ contract

    def _function(self, merged: Mapping[str, np.ndarray]):
        """The jitted render for this mapping: its class's own for one image, map + switch for a batch."""
        return self._batched if is_batched(merged) else self._single[SHAPES[int(merged["kappa"])]]

    def render(self, params: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Render the contract mapping; (H, W, 3) or (B, H, W, 3) float32 in [0, 1]."""
        merged = self.merged(params)
        return np.asarray(self._function(merged)(merged))

    def surface_ids(self, params: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Which surface each pixel sees: 0 nothing, 1 the floor, 2 the object. (H, W) or (B, H, W)."""
        merged = self.merged(params)
        if is_batched(merged):
            return np.stack([self.surface_ids(unbatch(merged, b)) for b in range(len(merged["shift"]))])
        return np.asarray(self._ids[SHAPES[int(merged["kappa"])]](merged)).astype(np.int32)

    def vjp(self, params: Mapping[str, np.ndarray] | None, cotangent: np.ndarray) -> dict[str, np.ndarray]:
        """Gradients of ``sum(render(params) * cotangent)`` for every float parameter.

        Pose gradients (shift, theta, scale) are zero: the geometry is under stop_gradient.
        """
        merged = self.merged(params)
        fn = self._function(merged)
        if fn not in self._vjps:
            self._vjps[fn] = jax.jit(lambda floats, kappa, cot: jax.vjp(
                lambda f: fn({**f, "kappa": kappa}), floats)[1](cot)[0])
        floats = {k: v for k, v in merged.items() if k != "kappa"}
        shape = (*np.shape(merged["shift"])[:-1], self.height, self.width, 3)
        grads = self._vjps[fn](floats, merged["kappa"], np.asarray(cotangent, np.float32).reshape(shape))
        return {k: np.asarray(v) for k, v in grads.items()}


__all__ = ["JaxRenderer", "camera_rays", "trace"]
