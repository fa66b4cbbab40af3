"""The renderer contract on Mitsuba 3 (the variant :mod:`mitsuba_p3.backend` picks), batched and differentiable.

Object geometry is never rebuilt. The three canonical shapes (see
:mod:`mitsuba_p3.shapes`) sit side by side in one fixed Mitsuba scene, each in its
own *slot*, and every camera ray is moved into its image's object frame (the
inverse of shift . yaw . scale) and over to the slot of its image's shape class.
A change of pose, size or class is therefore only per-ray arithmetic: no BVH
rebuild and no kernel recompilation, and a batch
of B parameter sets is a single launch of B*H*W rays. The floor z = 0 is
intersected analytically and shaded by a ``phong`` BSDF whose pattern is a
Mitsuba bitmap texture. Shading sums :func:`~mitsuba_p3.render.phong.phong_terms` over the lights;
with shadows on, each light's visibility is the share of its disc's fixed sample points that a
shadow ray reaches (:mod:`.soft_shadows`; one point, the centre, for hard shadows). Camera rays meet
the object in Mitsuba's scene; shadow rays only ask whether they are blocked, and that is answered
in closed form for the three canonical shapes, in the same kernel (:meth:`MitsubaRenderer._occluded`).

Gradients flow (Dr.Jit AD) to colours, materials, lights, ambient light and the
floor; the geometry is detached, since visibility edges make plain-AD pose
gradients wrong and the method never needs them (pose is sampled by MH).
"""
from __future__ import annotations

from typing import Mapping, Sequence

import numpy as np

from ..backend import jit_backend, mitsuba
from ..scene import Scene
from ..shapes import PARTS, SHAPES, part_dict
from .contract import Renderer, check_memory, is_batched

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the backend has chosen libLLVM)

from .drjit_params import DrParams, gradients_of, to_drjit, to_drjit_pattern  # noqa: E402
from . import hemisphere  # noqa: E402
from .lobes import ggx_term  # noqa: E402
from .falloff import falloff  # noqa: E402
from .phong import SHADOW_OFFSET, half_vector, phong_terms, pixel_centre_rays  # noqa: E402

_BACKEND = jit_backend()  # renders open a fresh scope of the chosen variant's backend

SLOT_SPACING = 8.0  # canonical units between the shape slots (shapes span 2 units)
_ENTRY_BACKOFF = 1e-3  # start object-space rays slightly before the box, in canonical units
_BOX_LO = (-1.0, -1.0, 0.0)
_BOX_HI = (1.0, 1.0, 2.0)


def _yaw(cos_t, sin_t, v):
    """Rotate a vector about z by theta (given its cosine and sine)."""
    return mi.Vector3f(cos_t * v.x - sin_t * v.y, sin_t * v.x + cos_t * v.y, v.z)


def _box_interval(origin, direction):
    """Entry and exit distances of rays through the canonical box [-1,1]^2 x [0,2]."""
    safe = dr.select(dr.abs(direction) > 1e-12, direction, dr.copysign(1e-12, direction))
    inv = dr.rcp(safe)
    t_a = (mi.Vector3f(*_BOX_LO) - origin) * inv
    t_b = (mi.Vector3f(*_BOX_HI) - origin) * inv
    t_near, t_far = dr.minimum(t_a, t_b), dr.maximum(t_a, t_b)
    return dr.max(t_near), dr.min(t_far)


def _within(t, reach):
    """Which distances ``t`` lie on a shadow ray: in [0, reach] (Mitsuba's own bounds test)."""
    return (t >= 0.0) & (t <= reach)


def _blocks_sphere(o, d, reach):
    """Whether rays (unit ``d``) meet the unit sphere about (0, 0, 1) within ``reach``; the
    closest-approach form, as the JAX tracer's, keeps float32 precise."""
    oc = o - mi.Vector3f(0.0, 0.0, 1.0)
    t_mid = -dr.dot(oc, d)
    closest = oc + t_mid * d
    r2 = dr.squared_norm(closest)
    half = dr.safe_sqrt(1.0 - r2)
    return (r2 <= 1.0) & (_within(t_mid - half, reach) | _within(t_mid + half, reach))


def _blocks_box(o, d, reach):
    """Whether rays meet the box [-1, 1]^2 x [0, 2] within ``reach`` (slabs)."""
    t_in, t_out = _box_interval(o, d)
    return (t_out >= dr.maximum(t_in, 0.0)) & (dr.maximum(t_in, 0.0) <= reach)


def _blocks_cylinder(o, d, reach):
    """Whether rays meet the closed cylinder x^2 + y^2 <= 1, 0 <= z <= 2 within ``reach``: its
    side (closest-approach quadratic in x, y) or either cap."""
    a = d.x * d.x + d.y * d.y
    a_safe = dr.select(a > 1e-20, a, 1.0)
    t_mid = -(o.x * d.x + o.y * d.y) / a_safe
    cx, cy = o.x + t_mid * d.x, o.y + t_mid * d.y
    r2 = cx * cx + cy * cy
    half = dr.safe_sqrt((1.0 - r2) / a_safe)
    side = (a > 1e-20) & (r2 <= 1.0)
    blocked = dr.zeros(mi.Bool, dr.width(a))
    for t in (t_mid - half, t_mid + half):
        z = o.z + t * d.z
        blocked |= side & _within(t, reach) & (z >= 0.0) & (z <= 2.0)
    dz = dr.select(dr.abs(d.z) > 1e-12, d.z, 1e-12)
    for height in (0.0, 2.0):
        t = (height - o.z) / dz
        x, y = o.x + t * d.x, o.y + t * d.y
        blocked |= _within(t, reach) & (x * x + y * y <= 1.0)
    return blocked


class MitsubaRenderer(Renderer):
    """Render the one-object Phong scene contract with Mitsuba.

    ``renderer.render(params)`` takes a mapping of named arrays (see
    :mod:`mitsuba_p3.render.contract`; keys not given keep the scene's values)
    and returns float32 images in [0, 1]: (H, W, 3), or (B, H, W, 3) when the
    object parameters carry a leading batch dimension. :meth:`render_drjit` is
    the same on Dr.Jit arrays with AD, for optimisation inside Dr.Jit, and
    :meth:`vjp` gives parameter gradients of ``sum(image * cotangent)``.
    """

    name = "mitsuba"

    def __init__(self, scene: Scene, height: int | None = None, width: int | None = None,
                 shadows: bool | None = None, shadow_samples: int | None = None):
        super().__init__(scene, height, width, shadows, shadow_samples)

        cam = scene.camera
        self._sensor = mi.load_dict({
            "type": "perspective", "fov": float(cam.fov), "fov_axis": "y",
            "to_world": mi.ScalarTransform4f().look_at(origin=cam.origin.tolist(), target=cam.target.tolist(),
                                                       up=cam.up.tolist()),
            "film": {"type": "hdrfilm", "width": self.width, "height": self.height,
                     "rfilter": {"type": "box"}},
        })
        rays = pixel_centre_rays(self._sensor)
        self._origin = mi.Point3f(*[float(v) for v in cam.origin])
        self._directions = mi.Vector3f(rays.d)
        dr.eval(self._directions)

        # The canonical shapes, one slot per class; their BSDF is never evaluated.
        holder = {"type": "diffuse"}
        shapes = {"type": "scene"}
        for kappa, name in enumerate(SHAPES):
            for i, part in enumerate(PARTS[name]):
                shapes[f"{name}_{i}"] = part_dict(part, holder, offset=(SLOT_SPACING * kappa, 0.0, 0.0))
        self._objects = mi.load_dict(shapes, optimize=False)

        self._floor = mi.load_dict({
            "type": "phong",
            "pattern": {"type": "bitmap", "bitmap": mi.Bitmap(self.params["floor_pattern"]), "raw": True,
                        "filter_type": "bilinear", "wrap_mode": "clamp"},
        })
        self._pattern_params = mi.traverse(self._floor.pattern)
        self._uploaded = {"pattern": None}  # the tensor the bitmap holds now (shared with window views)
        self._pattern_cache: tuple[np.ndarray, mi.TensorXf] | None = None

    def window(self, top: int, left: int, height: int, width: int) -> "MitsubaRenderer":
        """The same renderer restricted to a window of its pixels: rows ``top`` to ``top + height``,
        columns ``left`` to ``left + width``. Its renders are exactly that crop of the full image's,
        at the cost of the window's pixels only (a sampler that scores a window around the object
        pays for those pixels, not the empty floor's). Shares the scene, pattern and kernels."""
        import copy

        from ..errors import SceneError

        if not (0 <= top and 0 <= left and height >= 1 and width >= 1 and top + height <= self.height
                and left + width <= self.width):
            raise SceneError(f"window {height}x{width} at ({top}, {left}) does not fit a "
                             f"{self.height}x{self.width} image")
        view = copy.copy(self)
        rows = np.arange(top, top + height)[:, None] * self.width + np.arange(left, left + width)[None, :]
        view._directions = dr.gather(mi.Vector3f, self._directions, mi.UInt32(rows.reshape(-1).astype(np.uint32)))
        dr.eval(view._directions)
        view.height, view.width = int(height), int(width)
        return view

    # ------------------------------------------------------------------ params

    def _set_pattern(self, p: DrParams) -> None:
        """Give the floor's bitmap the pattern tensor (uploading only when it changed).

        The floor's ``phong`` BSDF supplies the floor albedo (colour x pattern); its
        Phong weights are read straight from the parameters in :meth:`_shade`.
        """
        if p.floor_pattern is not self._uploaded["pattern"]:
            self._pattern_params["data"] = p.floor_pattern
            self._pattern_params.update()
            self._uploaded["pattern"] = p.floor_pattern

    # ------------------------------------------------------------------ render
    def render_drjit(self, p: DrParams) -> mi.TensorXf:
        """Render on Dr.Jit arrays; returns a (B, H, W, 3) tensor that AD can differentiate."""
        # Renders may run on another thread than the one that made this renderer (JAX's
        # pure_callback runs on XLA's thread): a fresh Dr.Jit scope orders their variables.
        check_memory(p.batch * self.height * self.width, self.memory_limit)
        dr.detail.new_scope(_BACKEND)
        self._set_pattern(p)
        colour = self._shade(p)
        return mi.TensorXf(dr.ravel(colour), shape=(p.batch, self.height, self.width, 3))

    def render(self, params: Mapping[str, np.ndarray] | None = None, objects: bool = False):
        """Render the contract mapping; (H, W, 3) or (B, H, W, 3) float32 in [0, 1]. With ``objects``,
        also the pixels whose ray meets the object first, (H, W) or (B, H, W) bool, from the same rays
        and launch (the shading fields' object region, :meth:`~mitsuba_p3.infer.model.PosteriorCore._image`)."""
        merged = self.merged(params)
        if objects:
            return self._with_objects(merged, bases=False)
        image = self.render_drjit(self._to_drjit_cached(merged))
        out = image.numpy()
        return out if is_batched(merged) else out[0]

    def render_bases(self, params: Mapping[str, np.ndarray] | None = None, objects: bool = False):
        """The image's material bases, (H, W, 4, 3) or (B, H, W, 4, 3): A, D, S and F.

        On the object's pixels the image is ``clip(c (k_a A + k_d D) + k_s S)``: A is the
        ambient light, D and S the light sums of the Phong diffuse and specular terms.
        F is the image elsewhere (and 0 on the object). One render serves any colour and
        weights at this pose, class and shininess (:meth:`PosteriorModel.material_move`).
        With ``objects``, also the object's pixels, as :meth:`render`'s."""
        merged = self.merged(params)
        if objects:
            return self._with_objects(merged, bases=True)
        out = self._evaluated(merged, bases=True)[0]
        return out if is_batched(merged) else out[0]

    def _with_objects(self, merged: dict, bases: bool):
        out, covered = self._evaluated(merged, bases, objects=True)
        return (out, covered) if is_batched(merged) else (out[0], covered[0])

    @property
    def on_device(self) -> bool:
        """Whether renders run on a GPU (``cuda_ad_rgb``): where :meth:`render_into` pays, as images need
        not cross to the host and back (on the CPU :meth:`render`'s numpy copies are as fast)."""
        return _BACKEND == dr.JitBackend.CUDA

    @staticmethod
    def host_array(buffer) -> np.ndarray:
        """A numpy copy of a small array that may live on the device Dr.Jit renders on: a numpy array or
        a CPU buffer as it is, a device buffer (DLPack) through Dr.Jit's tensor of its type."""
        try:
            return np.asarray(buffer)
        except (TypeError, ValueError, RuntimeError):
            kind = {np.dtype(np.float32): "TensorXf", np.dtype(np.int32): "TensorXi"}[np.dtype(buffer.dtype)]
            return getattr(mi, kind)(buffer).numpy()

    def render_into(self, params: Mapping[str, np.ndarray] | None, image, covered=None, bases: bool = False) -> None:
        """Render the contract mapping straight into ``image``: a writable, C-ordered float32 array of
        B x H x W x 3 values (B x H x W x 4 x 3 with ``bases``; B the batch of ``params``, any shape with
        that many values) that Dr.Jit maps without a copy: a numpy array, or a JAX buffer through DLPack
        (:func:`mitsuba_p3.infer.render_functions.mitsuba_render_function`), on the CPU or the device
        Dr.Jit renders on. With ``covered`` (B x H x W float32), also the object's pixels (1 where the
        ray meets the object first). The same launch and values as :meth:`render` /
        :meth:`render_bases`; no image passes through the host."""
        p = self._to_drjit_cached(self.merged(params))
        pixels = p.batch * self.height * self.width
        outputs = [(image, 12 if bases else 3)] + ([(covered, 1)] if covered is not None else [])
        for output, per_pixel in outputs:     # checked before rendering; another dtype would be copied, not mapped
            if np.dtype(getattr(output, "dtype", None)) != np.float32 or np.prod(output.shape) != pixels * per_pixel:
                raise ValueError(f"render_into: an output of {getattr(output, 'dtype', None)} {tuple(output.shape)}, "
                                 f"expected float32 with {pixels} pixels x {per_pixel}")
        # the shading in one kernel (scattered from directly, Dr.Jit would trace it once per output),
        # then per output one small kernel that interleaves its channels into it, pixel-major
        flat, hit = self._channels(p, bases, objects=covered is not None)
        targets = [(mi.TensorXf(image).array, flat)] + ([(mi.TensorXf(covered).array, hit)] if hit else [])
        for target, values in targets:
            slot = dr.arange(mi.UInt32, pixels * len(values))
            pixel, channel = slot // len(values), slot % len(values)
            value = dr.zeros(mi.Float, dr.width(slot))
            for k, channel_values in enumerate(values):
                value = dr.select(channel == k, dr.gather(mi.Float, channel_values, pixel, channel == k), value)
            dr.scatter(target, value, slot)
        dr.eval(*(target for target, _ in targets))
        dr.sync_thread()    # written before the caller (XLA, on a device: its own stream) reads them

    def _evaluated(self, merged: dict, bases: bool, objects: bool = False) -> tuple:
        """(B, H, W, 3) colours, or (B, H, W, 4, 3) bases, and with ``objects`` the (B, H, W) object
        pixels, evaluated in one launch (no AD)."""
        p = self._to_drjit_cached(merged)
        flat, covered = self._channels(p, bases, objects)
        shape = (p.batch, self.height, self.width)
        out = np.stack([v.numpy() for v in flat], axis=-1).reshape(shape + ((4, 3) if bases else (3,)))
        return (out,) + tuple(v.numpy().reshape(shape) > 0.5 for v in covered)

    def _channels(self, p: DrParams, bases: bool, objects: bool) -> tuple[list, list]:
        """The render of ``p``, evaluated in one launch (no AD): a flat array per channel (3 colours, or
        the bases' 4 x 3) and, with ``objects``, [the object's pixels as 1.0 / 0.0] (else [])."""
        check_memory(p.batch * self.height * self.width, self.memory_limit, "bases" if bases else "image")
        dr.detail.new_scope(_BACKEND)  # see render_drjit
        self._set_pattern(p)
        shaded, hit_object = self._shade(p, bases=bases, objects=True)
        flat = [part[channel] for part in (shaded if bases else (shaded,)) for channel in range(3)]
        covered = [dr.select(hit_object, 1.0, 0.0)] if objects else []
        dr.eval(*flat, *covered)
        return flat, covered

    def vjp(self, params: Mapping[str, np.ndarray] | None, cotangent: np.ndarray) -> dict[str, np.ndarray]:
        """Gradients of ``sum(render(params) * cotangent)`` for every float parameter.

        Pose gradients (shift, theta, scale) are zero: the geometry is detached.
        """
        merged = self.merged(params)
        p = to_drjit(merged)
        targets = p.differentiable()
        for value in targets.values():
            dr.enable_grad(value)
        image = self.render_drjit(p)
        cot = np.asarray(cotangent, np.float32).reshape(image.shape)
        dr.backward(dr.sum(image.array * mi.Float(cot.reshape(-1))))
        return gradients_of(targets, merged)

    def loss_and_grad(self, params: Mapping[str, np.ndarray] | None, target: mi.Float,
                      keys: Sequence[str]) -> tuple[float, dict[str, np.ndarray]]:
        """Mean squared error to ``target`` (a flat Dr.Jit array of the image) and its
        gradients with respect to ``keys``, in one forward and one backward pass."""
        merged = self.merged(params)
        p = self._to_drjit_cached(merged) if "floor_pattern" not in keys else to_drjit(merged)
        targets = {key: getattr(p, key) for key in keys}
        for value in targets.values():
            dr.enable_grad(value)
        image = self.render_drjit(p)
        loss = dr.mean(dr.square(image.array - target))
        dr.backward(loss)
        return float(loss[0]), gradients_of(targets, merged)

    def _to_drjit_cached(self, merged: Mapping[str, np.ndarray]) -> DrParams:
        """:func:`to_drjit`, reusing the pattern tensor while it is unchanged (no re-upload)."""
        pattern = merged["floor_pattern"]
        cached = self._pattern_cache
        if cached is None or cached[0].shape != pattern.shape or not np.array_equal(cached[0], pattern):
            cached = self._pattern_cache = (np.array(pattern, copy=True), to_drjit_pattern(pattern))
        return to_drjit(merged, pattern=cached[1])

    # ------------------------------------------------------------------ core
    def _object_frame(self, p: DrParams, batch_index):
        """Per-ray object transform pieces: (cos, sin, shift as 3-vector, scale, slot offset)."""
        gather = (lambda cls, value: dr.gather(cls, value, batch_index)) if batch_index is not None else (
            lambda cls, value: value)
        theta = gather(mi.Float, p.theta)
        shift = gather(mi.Point2f, p.shift)
        scale = gather(mi.Vector3f, p.scale)
        slot = mi.Float(gather(mi.UInt32, p.kappa)) * SLOT_SPACING
        return dr.cos(theta), dr.sin(theta), mi.Vector3f(shift.x, shift.y, 0.0), scale, slot

    def _to_object(self, frame, point, direction):
        """World ray -> canonical ray in its slot: (origin, unit direction, length of unscaled direction)."""
        cos_t, sin_t, shift, scale, slot = frame
        origin = _yaw(cos_t, -sin_t, point - shift) / scale
        direction = _yaw(cos_t, -sin_t, direction) / scale
        length = dr.norm(direction)
        return origin + mi.Vector3f(slot, 0.0, 0.0), direction / length, length

    def _trace_object(self, frame, origin_w, direction_w):
        """Intersect world rays with the object. Returns (hit, world distance, world normal)."""
        origin, direction, length = self._to_object(frame, origin_w, direction_w)
        slot = frame[4]
        t_in, t_out = _box_interval(origin - mi.Vector3f(slot, 0.0, 0.0), direction)
        # Rays from outside start just before the box (so far-away slots are never reached);
        # rays from inside start at their origin.
        start = dr.select(t_in > 0, t_in - _ENTRY_BACKOFF, 0.0)
        reach = t_out - start + _ENTRY_BACKOFF
        active = (t_out >= dr.maximum(t_in, 0.0)) & (reach > 0)
        ray = mi.Ray3f(origin + direction * start, direction, dr.maximum(reach, 0.0))
        si = self._objects.ray_intersect(ray, ray_flags=mi.RayFlags.Minimal | mi.RayFlags.ShadingFrame,
                                         coherent=True, active=active)
        cos_t, sin_t, _, scale, _ = frame
        normal = dr.normalize(_yaw(cos_t, sin_t, si.sh_frame.n / scale))
        return si.is_valid(), (start + si.t) / length, normal

    def _occluded(self, frame, origin_w, direction_w, max_t, active=True):
        """Whether shadow rays (unit world ``direction_w``) meet the object within ``max_t``: the
        canonical shapes' occlusion in closed form, Dr.Jit arithmetic inside the render's kernel.
        It gives the answer of Mitsuba's scene (the first hit of :meth:`_trace_object`, if within
        ``max_t``: the reference in tests/test_render.py) without a ray-tracing call out of the
        kernel per light."""
        origin, direction, length = self._to_object(frame, origin_w, direction_w)
        slot = frame[4]
        origin = origin - mi.Vector3f(slot, 0.0, 0.0)
        reach = max_t * length
        blocked = dr.select(slot < 0.5 * SLOT_SPACING, _blocks_sphere(origin, direction, reach),
                            dr.select(slot < 1.5 * SLOT_SPACING, _blocks_box(origin, direction, reach),
                                      _blocks_cylinder(origin, direction, reach)))
        return blocked & active

    def _rays(self, p: DrParams, differentiating: bool = False):
        """Per-ray batch index (None for an unbatched, non-AD render) and camera direction."""
        hw = self.height * self.width
        if p.batch == 1:
            return (dr.zeros(mi.UInt32, hw) if differentiating else None), self._directions
        index = dr.arange(mi.UInt32, p.batch * hw)
        batch_index = index // hw
        return batch_index, dr.gather(mi.Vector3f, self._directions, index - batch_index * hw)

    def _geometry(self, p: DrParams, batch_index, direction):
        """First hits, detached: (frame, hit_object, hit_floor, point, normal, floor_point)."""
        origin = self._origin
        with dr.suspend_grad():  # geometry: no pose gradients (see module docstring)
            frame = self._object_frame(p, batch_index)
            hit_object, t_object, n_object = self._trace_object(frame, origin, direction)
            t_floor = -origin.z / direction.z
            floor_point = origin + t_floor * direction
            h = self.floor_half_size
            hit_floor = (direction.z < 0) & (t_floor > 0) & (dr.abs(floor_point.x) <= h) & (
                dr.abs(floor_point.y) <= h)
            hit_object &= ~hit_floor | (t_object < t_floor)
            hit_floor &= ~hit_object
            t = dr.select(hit_object, t_object, t_floor)
            point = origin + t * direction
            normal = dr.select(hit_object, n_object, mi.Vector3f(0.0, 0.0, 1.0))
        return frame, hit_object, hit_floor, point, normal, floor_point

    def surface_ids(self, params: Mapping[str, np.ndarray] | None = None) -> np.ndarray:
        """Which surface each pixel sees: 0 nothing, 1 the floor, 2 the object. (H, W) or (B, H, W)."""
        merged = self.merged(params)
        p = self._to_drjit_cached(merged)
        batch_index, direction = self._rays(p)
        _, hit_object, hit_floor, *_ = self._geometry(p, batch_index, direction)
        ids = dr.select(hit_object, 2, dr.select(hit_floor, 1, 0))
        out = mi.UInt32(ids).numpy().astype(np.int32).reshape(p.batch, self.height, self.width)
        return out if is_batched(merged) else out[0]

    def _visibility(self, frame, point, normal, centre, radius, active):
        """The share of the light's disc (radius ``radius`` about ``centre``, facing the point) that
        shadow rays from just above ``point`` reach past the object: 0 or 1 for one sample."""
        start = point + normal * SHADOW_OFFSET
        if self.shadow_samples == 1:  # the light's centre, as seen from the point itself
            to_light = centre - point
            distance = dr.norm(to_light)
            occluded = self._occluded(frame, start, to_light / distance, distance, active=active)
            return dr.select(occluded, 0.0, 1.0)
        axis = dr.normalize(centre - start)
        # Duff et al.'s orthonormal basis about the axis (the JAX tracer uses the same formula)
        sign = dr.select(axis.z >= 0, 1.0, -1.0)
        a = -1.0 / (sign + axis.z)
        b = axis.x * axis.y * a
        first = mi.Vector3f(1.0 + sign * axis.x * axis.x * a, sign * b, -sign * axis.x)
        second = mi.Vector3f(b, sign + axis.y * axis.y * a, -axis.y)
        visible = mi.Float(0.0)
        weight = 1.0 / self.shadow_samples
        for x, y in self.shadow_pattern.tolist():
            to_light = centre + radius * (x * first + y * second) - start
            distance = dr.norm(to_light)
            occluded = self._occluded(frame, start, to_light / distance, distance, active=active)
            visible += dr.select(occluded, 0.0, weight)
        return visible

    def _shade(self, p: DrParams, bases: bool = False, objects: bool = False):
        """The image's colours per ray or, with ``bases``, its material bases (A, D, S, F); with
        ``objects``, (that, whether each ray meets the object first)."""
        rays = p.batch * self.height * self.width
        differentiating = any(dr.grad_enabled(v) for v in p.differentiable().values())
        batch_index, direction = self._rays(p, differentiating)

        def per_ray(cls, value, index=None):
            """A parameter at every ray. Under AD, width-1 values are gathered too: the
            adjoint of a gather is a scatter-add, and all of them fuse into one backward
            kernel, where a width-1 broadcast would cost one re-traced kernel per parameter."""
            if index is not None:
                return dr.gather(cls, value, index)
            return dr.gather(cls, value, dr.zeros(mi.UInt32, rays)) if differentiating else value

        frame, hit_object, hit_floor, point, normal, floor_point = self._geometry(p, batch_index, direction)
        view = -direction
        valid = hit_object | hit_floor
        h = self.floor_half_size

        floor = self._floor
        floor.colour = per_ray(mi.Color3f, p.floor_colour)
        floor_si = dr.zeros(mi.SurfaceInteraction3f)
        floor_si.uv = mi.Point2f((floor_point.x / h + 1.0) * 0.5, (floor_point.y / h + 1.0) * 0.5)
        albedo = dr.select(hit_object, per_ray(mi.Color3f, p.colour, batch_index), floor.albedo(floor_si, hit_floor))
        ambient = dr.select(hit_object, per_ray(mi.Float, p.ambient, batch_index), per_ray(mi.Float, p.floor_ambient))
        diffuse = dr.select(hit_object, per_ray(mi.Float, p.diffuse, batch_index), per_ray(mi.Float, p.floor_diffuse))
        specular = dr.select(hit_object, per_ray(mi.Float, p.specular, batch_index),
                             per_ray(mi.Float, p.floor_specular))
        shininess = dr.select(hit_object, per_ray(mi.Float, p.shininess, batch_index),
                              per_ray(mi.Float, p.floor_shininess))

        # The Phong sum as two light sums, D = sum I_l [n.l > 0] n.l and
        # S = sum I_l [n.l > 0] max(0, r.v)^alpha (or the GGX lobe, render/lobes.py):
        # the image is k_a c A + k_d c D + k_s S.
        ambient_light = per_ray(mi.Color3f, p.ambient_light)
        lit_diffuse, lit_specular = mi.Color3f(0.0), mi.Color3f(0.0)
        for k in range(dr.width(p.light_position)):
            light = dr.full(mi.UInt32, k, rays) if differentiating else mi.UInt32(k)
            position = dr.gather(mi.Point3f, p.light_position, light)
            intensity = dr.gather(mi.Color3f, p.light_intensity, light)
            to_light = position - point
            distance = dr.norm(to_light)
            direction_l = to_light / distance
            cos_light = dr.dot(normal, direction_l)
            if self.lobe == "ggx":
                diffuse_term = dr.select(cos_light > 0, cos_light, 0.0)
                specular_term = dr.select(cos_light > 0, ggx_term(
                    shininess, diffuse_term, dr.maximum(dr.dot(normal, view), 0.0),
                    dr.dot(normal, half_vector(direction_l, view)), dr.sqrt), 0.0)
            else:
                reflected = 2.0 * cos_light * normal - direction_l
                diffuse_term, specular_term = phong_terms(shininess, cos_light, dr.dot(reflected, view))
            if self.shadows:
                with dr.suspend_grad():
                    visible = self._visibility(frame, point, normal, dr.detach(position),
                                               dr.detach(p.light_radius), valid & (cos_light > 0))
                diffuse_term = diffuse_term * visible
                specular_term = specular_term * visible
            if self.falloff:   # inverse-square falloff about the reference distance (render/falloff.py)
                intensity = intensity * falloff(per_ray(mi.Float, p.light_falloff), distance)
            lit_diffuse += intensity * diffuse_term
            lit_specular += intensity * specular_term
        # the environment as two hemispheres (render/hemisphere.py): zero unless the world has a sky or ground
        if self.environment:
            sky, ground = per_ray(mi.Color3f, p.sky), per_ray(mi.Color3f, p.ground)
            lit_diffuse += hemisphere.diffuse_term(normal.z, sky, ground)
            reflected_z = 2.0 * dr.dot(normal, view) * normal.z - view.z
            lit_specular += hemisphere.specular_term(reflected_z, shininess, sky, ground, dr.asin, dr.erf, dr.sqrt,
                                                     dr.clip)
        result = albedo * (ambient * ambient_light + diffuse * lit_diffuse) + specular * lit_specular
        image = dr.select(valid, dr.clip(result, 0.0, 1.0), 0.0)
        if bases:
            image = (dr.select(hit_object, ambient_light, 0.0), dr.select(hit_object, lit_diffuse, 0.0),
                     dr.select(hit_object, lit_specular, 0.0), dr.select(hit_object, 0.0, image))
        return (image, hit_object) if objects else image
