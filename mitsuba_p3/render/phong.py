"""Mitsuba plugins of the Phong model: the ``phong`` BSDF and the ``phong_integrator``.

The one Phong model of the project (shared/ARCHITECTURE.md) is

    I = k_a c A + sum_l V_l I_l (k_d c max(0, n.l) + k_s max(0, r.v)^alpha [n.l > 0])

with c the albedo, A the ambient light, I_l a point light's RGB intensity (no
distance fall-off) and V_l its visibility (1 with shadows off). It predicts
display pixel values directly and is clipped to [0, 1]. :func:`phong_lobes` is
the per-light term (the BSDF's ``eval``); the renderers sum :func:`phong_terms`
over the lights, so that the image is affine in the materials.
"""
from __future__ import annotations

from ..backend import mitsuba

mi = mitsuba()
import drjit as dr  # noqa: E402  (after the backend has chosen libLLVM)

# Shadow rays leave the surface this far (metres) along the normal; objects are >= 1 cm.
SHADOW_OFFSET = 1e-4
# A floor for max(0, r.v) before the power, so that d/d(alpha) of 0^alpha stays 0, not NaN.
_TINY = 1e-30


def phong_terms(shininess, cos_light, cos_reflect):
    """The per-light Phong terms before the materials: ([n.l > 0] n.l, [n.l > 0] max(0, r.v)^alpha).

    ``cos_light`` is n.l and ``cos_reflect`` is r.v (r: the light direction mirrored
    about n, v: towards the viewer); both are zero where the light is behind the surface.
    """
    from .lobes import sharpness

    lit = cos_light > 0
    cos_r = dr.maximum(cos_reflect, _TINY)
    highlight = dr.select(cos_reflect > 0, dr.exp(sharpness(shininess) * dr.log(cos_r)), 0.0)
    return dr.select(lit, cos_light, 0.0), dr.select(lit, highlight, 0.0)


def phong_lobes(albedo, diffuse, specular, shininess, cos_light, cos_reflect):
    """Diffuse plus specular Phong reflection for one light of unit intensity:
    k_d c max(0, n.l) + k_s max(0, r.v)^alpha, zero where n.l <= 0 (see :func:`phong_terms`)."""
    diffuse_term, specular_term = phong_terms(shininess, cos_light, cos_reflect)
    return diffuse * albedo * diffuse_term + specular * specular_term


def half_vector(light, view):
    """(l + v) / |l + v|, zero (not NaN, nor a NaN gradient) where the light is straight behind."""
    total = light + view
    return total * dr.rsqrt(dr.maximum(dr.squared_norm(total), 1e-12))


def _as_colour(value):
    """A property given as rgb (or a number) becomes a Color3f; textures stay textures."""
    if isinstance(value, mi.Texture):
        return value
    if isinstance(value, (int, float)):
        return mi.Color3f(float(value))
    return mi.Color3f(value)


class PhongBSDF(mi.BSDF):
    """Phong reflection (``phong``): Lambertian diffuse plus a Phong highlight.

    .. pluginparameters::

     * - colour
       - |spectrum| or |texture|
       - Albedo c of the diffuse and ambient terms. (Default: 0.5)
     * - pattern
       - |texture|
       - Optional texture multiplying the colour, e.g. the floor's pattern
         (use ``raw=true`` bitmaps: values are display values). (Default: none)
     * - ambient
       - |float|
       - k_a, the weight of the ambient term k_a c A (A: the integrator's ambient light). (Default: 0.1)
     * - diffuse
       - |float|
       - k_d, the weight of the diffuse term k_d c max(0, n.l). (Default: 0.9)
     * - specular
       - |float|
       - k_s, the weight of the untinted highlight k_s max(0, r.v)^alpha. (Default: 0.5)
     * - shininess
       - |float|
       - alpha, the Phong exponent. (Default: 4)
     * - lobe
       - |string|
       - The specular lobe: ``phong`` (k_s max(0, r.v)^alpha) or ``ggx`` (a GGX microfacet lobe of
         roughness a^2 = 2 / (alpha + 2), :mod:`mitsuba_p3.render.lobes`). (Default: phong)

    ``eval`` returns the per-light Phong term (:func:`phong_lobes`) for a light in
    direction ``wo``; as in Mitsuba's convention it already contains the cosine of
    the diffuse lobe. The ambient term is not a BSDF notion: it is exposed as the
    attribute ``ambient_reflectance`` (k_a c) for the ``phong`` integrator. The model
    is evaluated, not sampled: ``sample`` returns an empty sample.
    """

    def __init__(self, props):
        super().__init__(props)
        self.colour = _as_colour(props.get("colour", 0.5))
        self.pattern = props["pattern"] if "pattern" in props else None
        self.ambient = mi.Float(props.get("ambient", 0.1))
        self.diffuse = mi.Float(props.get("diffuse", 0.9))
        self.specular = mi.Float(props.get("specular", 0.5))
        self.shininess = mi.Float(props.get("shininess", 4.0))
        from .lobes import check_lobe

        self.lobe = check_lobe(props.get("lobe", "phong"))
        self.parameters_changed()
        self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide
        self.m_components = [mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide,
                             mi.BSDFFlags.GlossyReflection | mi.BSDFFlags.FrontSide]

    def albedo(self, si, active=True):
        """c at the surface point: the colour (or colour texture) times the pattern."""
        c = self.colour.eval(si, active) if isinstance(self.colour, mi.Texture) else self.colour
        if self.pattern is not None:
            c = c * self.pattern.eval(si, active)
        return c

    def eval(self, ctx, si, wo, active=True):
        cos_light = mi.Frame3f.cos_theta(wo)
        if self.lobe == "ggx":
            from .lobes import ggx_term

            lit = cos_light > 0
            cos_view = dr.maximum(mi.Frame3f.cos_theta(si.wi), 0.0)
            half = half_vector(wo, si.wi)
            highlight = ggx_term(self.shininess, dr.maximum(cos_light, 0.0), cos_view, half.z, dr.sqrt)
            value = dr.select(lit, self.diffuse * self.albedo(si, active) * cos_light + self.specular * highlight, 0.0)
        else:
            cos_reflect = dr.dot(mi.reflect(wo), si.wi)
            value = phong_lobes(self.albedo(si, active), self.diffuse, self.specular, self.shininess,
                                cos_light, cos_reflect)
        return dr.select(active, value, 0.0)

    def sample(self, ctx, si, sample1, sample2, active=True):
        return dr.zeros(mi.BSDFSample3f), mi.Color3f(0.0)

    def pdf(self, ctx, si, wo, active=True):
        return mi.Float(0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return self.eval(ctx, si, wo, active), mi.Float(0.0)

    def eval_diffuse_reflectance(self, si, active=True):
        return self.diffuse * self.albedo(si, active)

    def eval_attribute_3(self, name, si, active=True):
        if name == "ambient_reflectance":
            return self.ambient * self.albedo(si, active)
        if name == "albedo":
            return self.albedo(si, active)
        return mi.Color3f(0.0)

    def eval_attribute_1(self, name, si, active=True):
        value = {"ambient": self.ambient, "diffuse": self.diffuse, "specular": self.specular,
                 "shininess": self.shininess}.get(name)
        return mi.Float(0.0) if value is None else mi.Float(value)

    def traverse(self, callback):
        flags = mi.ParamFlags.Differentiable
        if isinstance(self.colour, mi.Texture):
            callback.put("colour", self.colour, flags)
        else:
            callback.put("colour", self.colour, flags)
        if self.pattern is not None:
            callback.put("pattern", self.pattern, flags)
        for name in ("ambient", "diffuse", "specular", "shininess"):
            callback.put(name, getattr(self, name), flags)

    def parameters_changed(self, keys=[]):
        # Keep values out of the compiled kernels: a new value must not recompile.
        dr.make_opaque(self.ambient, self.diffuse, self.specular, self.shininess)
        if not isinstance(self.colour, mi.Texture):
            dr.make_opaque(self.colour)

    def to_string(self):
        return (f"PhongBSDF[colour={self.colour}, pattern={self.pattern is not None}, "
                f"ambient={self.ambient}, diffuse={self.diffuse}, specular={self.specular}, "
                f"shininess={self.shininess}, lobe={self.lobe}]")


def pixel_centre_rays(sensor) -> mi.Ray3f:
    """One camera ray through the centre of every film pixel, row-major from the top left."""
    width, height = (int(v) for v in sensor.film().crop_size())
    index = dr.arange(mi.UInt32, width * height)
    row = index // width
    col = index - row * width
    position = mi.Point2f((mi.Float(col) + 0.5) / width, (mi.Float(row) + 0.5) / height)
    ray, _ = sensor.sample_ray(time=0.0, sample1=0.5, sample2=position, sample3=mi.Point2f(0.5))
    return mi.Ray3f(ray)


def point_lights(scene) -> list[tuple[mi.Point3f, mi.Color3f]]:
    """(position, intensity) of every point emitter of a scene, read from its parameters."""
    lights = []
    for emitter in scene.emitters():
        params = mi.traverse(emitter)
        if "position" not in params.keys():
            raise ValueError(f"the phong integrator supports point lights only, found {emitter}")
        lights.append((mi.Point3f(params["position"]), mi.Color3f(params["intensity.value"])))
    return lights


class PhongIntegrator(mi.SamplingIntegrator):
    """Deterministic Phong shading (``phong_integrator``) of any scene with point lights.

    .. pluginparameters::

     * - ambient
       - |spectrum|
       - The ambient light A of the term k_a c A. (Default: 1)
     * - shadows
       - |bool|
       - Shadows: shadow rays towards every light (V_l). (Default: false)
     * - light_radius
       - |float|
       - Every light widened into a disc of this radius (metres) facing the shaded point: V_l is
         the share of its fixed sample points a shadow ray reaches (soft shadows,
         :mod:`mitsuba_p3.render.soft_shadows`). 0: point lights, hard shadows. (Default: 0)
     * - sky, ground
       - |spectrum|
       - Radiance of the environment above and below the horizon, added to the diffuse and specular
         light sums (:mod:`mitsuba_p3.render.hemisphere`). (Default: 0, 0)
     * - light_falloff
       - |float|
       - A reference distance d0 (metres): every light's intensity falls off as (d0 / d)^2 with its
         distance d, as a physical light's does (:func:`falloff`). 0: no falloff, the Phong model's
         convention and the paper's. (Default: 0)

    Every point light is evaluated at every hit (Mitsuba's ``direct`` picks one at
    random), with no distance fall-off unless ``light_falloff`` asks for it, and rays
    go through pixel centres, so an image is a deterministic function of the scene
    parameters: one sample per pixel suffices and ``spp`` is ignored. Surfaces must
    use the ``phong`` BSDF.
    """

    def __init__(self, props):
        super().__init__(props)
        self.ambient = mi.Color3f(props.get("ambient", 1.0))
        self.shadows = bool(props.get("shadows", False))
        self.light_radius = float(props.get("light_radius", 0.0))
        self.light_falloff = float(props.get("light_falloff", 0.0))
        self.sky = mi.Color3f(props.get("sky", 0.0))
        self.ground = mi.Color3f(props.get("ground", 0.0))
        self.environment = bool(dr.any(self.sky > 0) | dr.any(self.ground > 0))
        from .soft_shadows import disc_pattern, samples_for

        self.pattern = disc_pattern(samples_for(self.light_radius))

    def shade(self, scene, ray: mi.Ray3f, active=True) -> tuple[mi.Color3f, mi.Bool]:
        """Phong radiance along each ray and whether it hit anything."""
        si = scene.ray_intersect(ray, active)
        valid = si.is_valid()
        # Refine: intersecting again from just before the hit recovers the float32 precision a
        # distant camera costs (visible as shadow acne on small, scaled instances).
        back_off = dr.maximum(si.t * 0.05, 1e-3)
        refined = scene.ray_intersect(mi.Ray3f(ray.o + ray.d * (si.t - back_off), ray.d), valid)
        refined.t += si.t - back_off
        si = dr.select(valid & refined.is_valid(), refined, si)
        bsdf = si.bsdf(ray)
        result = bsdf.eval_attribute_3("ambient_reflectance", si, valid) * self.ambient
        if self.environment:
            from . import hemisphere

            normal, view = si.sh_frame.n, -ray.d
            shininess = bsdf.eval_attribute_1("shininess", si, valid)
            result += bsdf.eval_diffuse_reflectance(si, valid) * hemisphere.diffuse_term(normal.z, self.sky,
                                                                                         self.ground)
            result += bsdf.eval_attribute_1("specular", si, valid) * hemisphere.specular_term(
                2.0 * dr.dot(normal, view) * normal.z - view.z, shininess, self.sky, self.ground, dr.asin, dr.erf,
                dr.sqrt, dr.clip)
        ctx = mi.BSDFContext()
        for position, intensity in point_lights(scene):
            to_light = position - si.p
            distance = dr.norm(to_light)
            direction = to_light / distance
            value = bsdf.eval(ctx, si, si.to_local(direction), valid)
            if self.shadows:
                # An explicit offset: spawn_ray_to's error bound is too tight for scaled instances.
                origin = si.p + si.n * SHADOW_OFFSET
                lit = valid & (value.x + value.y + value.z > 0)
                if len(self.pattern) == 1:
                    shadow_ray = mi.Ray3f(origin, direction, dr.norm(position - origin))
                    value = dr.select(scene.ray_test(shadow_ray, lit), 0.0, value)
                else:
                    first, second = mi.coordinate_system(dr.normalize(position - origin))
                    visible = mi.Float(0.0)
                    for x, y in self.pattern.tolist():
                        target = position + self.light_radius * (x * first + y * second)
                        shadow_ray = mi.Ray3f(origin, dr.normalize(target - origin), dr.norm(target - origin))
                        visible += dr.select(scene.ray_test(shadow_ray, lit), 0.0, 1.0 / len(self.pattern))
                    value = value * visible
            if self.light_falloff > 0:
                from .falloff import falloff

                value = value * falloff(self.light_falloff, distance)
            result += intensity * value
        return dr.select(valid, dr.clip(result, 0.0, 1.0), 0.0), valid

    def sample(self, scene, sampler, ray, medium=None, active=True):
        colour, valid = self.shade(scene, mi.Ray3f(ray), active)
        return colour, valid, []

    def render(self, scene, sensor=0, seed=0, spp=0, develop=True, evaluate=True):
        if isinstance(sensor, int):
            sensor = scene.sensors()[sensor]
        width, height = (int(v) for v in sensor.film().crop_size())
        colour, _ = self.shade(scene, pixel_centre_rays(sensor))
        image = mi.TensorXf(dr.ravel(colour), shape=(height, width, 3))
        # Evaluate now: the lazy kernel references the scene's BVH, and a caller may drop
        # the scene (mi.render(mi.load_file(...))) before reading the image -> segfault.
        dr.eval(image)
        return image

    def to_string(self):
        return (f"PhongIntegrator[ambient={self.ambient}, shadows={self.shadows}, "
                f"light_radius={self.light_radius}, light_falloff={self.light_falloff}]")


_REGISTERED = False
# Mitsuba's plugin registry is keyed by name alone: the BSDF and the integrator need distinct names.
BSDF = "phong"
INTEGRATOR = "phong_integrator"


def register() -> None:
    """Register the ``phong`` BSDF and the ``phong_integrator`` with Mitsuba (idempotent)."""
    global _REGISTERED
    if not _REGISTERED:
        mi.register_bsdf(BSDF, lambda props: PhongBSDF(props))
        mi.register_integrator(INTEGRATOR, lambda props: PhongIntegrator(props))
        _REGISTERED = True


register()  # importing this module makes 'phong' and 'phong_integrator' loadable
