"""Write the scene files of each benchmark variant (and their textures and meshes).

- scenes/VARIANT.xml: the Phong model's scene (phong_integrator), what inference fits;
- scenes/benchmarks/VARIANT.xml: the path-traced world the benchmark images are made
  with (`mitsuba-p3 benchmark generate`), with scenes/benchmarks/{textures,meshes}/.

The XML files are the source of truth: edit them by hand to change a benchmark.
This script only regenerates them from the values below. Usage:

    python scripts/make_scenes.py [--out scenes]
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import gaussian_filter

from mitsuba_p3.scene import Floor, PhongMaterial, PointLight, Scene, SceneObject, save_scene

# Tabletop-scale stand-ins for CLEVR's warm key, cool fill and back lights (metres, RGB).
LIGHTS = [
    PointLight(np.array([0.30, -0.35, 0.45]), np.array([0.62, 0.56, 0.48])),   # key, warm
    PointLight(np.array([-0.40, -0.25, 0.30]), np.array([0.18, 0.20, 0.26])),  # fill, cool
    PointLight(np.array([0.05, 0.45, 0.40]), np.array([0.25, 0.25, 0.25])),   # back
]
PLAIN_FLOOR = PhongMaterial(np.full(3, 0.55), ambient=0.25, diffuse=0.75, specular=0.0, shininess=1.0)


def wood_pattern(size: int = 200, seed: int = 7) -> np.ndarray:
    """A deterministic wood-plank pattern, (size, size, 3) in [0, 1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    grain = gaussian_filter(rng.normal(size=(size, size)), sigma=(size / 12, size / 60))
    grain /= np.abs(grain).max()
    planks = np.floor(x * 5)
    offset = rng.uniform(0, 1, size=5)[planks.astype(int)]
    rings = 0.5 + 0.5 * np.sin(2 * np.pi * (18 * (y + offset) + 3 * grain))
    tone = 0.55 + 0.25 * rings + 0.1 * rng.uniform(-1, 1, size=5)[planks.astype(int)]
    seam = (np.abs((x * 5) % 1.0) < 0.02)
    base = np.array([0.62, 0.40, 0.22])
    image = tone[..., None] * base / 0.8
    image[seam] *= 0.45
    return np.clip(image, 0, 1).astype(np.float32)


def variant(name: str) -> tuple[Scene, str]:
    obj = SceneObject("sphere", np.zeros(2), 0.0, np.full(3, 0.035),
                      PhongMaterial.named("red", "rubber"))
    scene = Scene(lights=[PointLight(l.position.copy(), l.intensity.copy()) for l in LIGHTS],
                  ambient_light=np.ones(3), floor=Floor(PLAIN_FLOOR), object=obj)
    if name == "fsclvr":
        return scene, "fsclvr: plain grey floor, warm key, cool fill and back light"
    if name == "dark":
        for light in scene.lights:
            light.intensity = light.intensity * 0.25
        scene.ambient_light = scene.ambient_light * 0.25
        return scene, "dark: fsclvr with every light (and the ambient light) at 25% strength"
    if name == "room":
        scene.floor = Floor(PhongMaterial(np.ones(3), 0.25, 0.75, 0.05, 8.0), pattern=wood_pattern(),
                            pattern_file="textures/wood.png")
        return scene, "room: a wooden floor under fsclvr's lights"
    if name == "ood":
        return scene, "ood: the fsclvr world (out-of-distribution objects reuse the fsclvr fit)"
    raise ValueError(name)


# ---------------------------------------------------------------- path-traced worlds
# Area lights (name, position, RGB radiance); rectangles of half-size LIGHT_HALF_SIZE facing the origin.
AREA_LIGHTS = [
    ("key", (0.30, -0.35, 0.45), (44.0, 39.0, 32.0)),    # warm
    ("fill", (-0.40, -0.25, 0.30), (10.0, 11.5, 14.0)),  # cool
    ("back", (0.05, 0.40, 0.40), (18.0, 18.0, 18.0)),
]
LIGHT_HALF_SIZE = 0.06
LIGHT_JITTER = 0.03     # metres, per axis, per image
SKY = 0.6               # a large, dim overhead panel: CLEVR's weak sun/sky (low-noise, unlike an environment)


def plank_tiles(size: int = 256, seed: int = 11) -> np.ndarray:
    """Pale wall tiles with grout lines, (size, size, 3) in [0, 1]."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:size, 0:size] / size
    tiles = 4
    cell = (np.floor(x * tiles) + tiles * np.floor(y * tiles)).astype(int)
    tone = 0.78 + 0.06 * rng.uniform(-1, 1, size=tiles * tiles)[cell]
    grout = (np.abs((x * tiles) % 1.0) < 0.03) | (np.abs((y * tiles) % 1.0) < 0.03)
    image = tone[..., None] * np.array([0.85, 0.92, 0.88])
    image[grout] = 0.35
    return np.clip(image, 0, 1).astype(np.float32)


def _bsdf_diffuse(colour=None, texture=None, uv_scale=1.0) -> str:
    if texture:
        return (f'<bsdf type="diffuse"><texture type="bitmap" name="reflectance">'
                f'<string name="filename" value="{texture}" />'
                f'<transform name="to_uv"><scale value="{uv_scale}" /></transform></texture></bsdf>')
    return f'<bsdf type="diffuse"><rgb name="reflectance" value="{colour}" /></bsdf>'


def world_xml(name: str) -> str:
    """The path-traced benchmark world of a variant (see mitsuba_p3/benchmarks/generate.py)."""
    from mitsuba_p3.benchmarks.meshes import MESH_NAMES

    strength = 0.25 if name == "dark" else 1.0
    lights = AREA_LIGHTS
    descriptions = {
        "fsclvr": "plain grey floor; warm key, cool fill and back area lights",
        "dark": "fsclvr with every light at 25% strength",
        "room": "wooden floor and tiled walls behind the object; fsclvr's lights",
        "ood": "the fsclvr world with ten everyday objects instead of primitives",
    }
    out = [f"""<?xml version="1.0" encoding="utf-8"?>
<!-- mitsuba-p3 benchmark world: {name}: {descriptions[name]}.
     Rendered by `mitsuba-p3 benchmark generate {name}` with Mitsuba's path tracer.
     Units are metres, z is up, the floor is z = 0. The first block of defaults is set
     per image by the generator: object (a shape group id below), material (rubber or
     metal), colour (linear RGB), scale (half-extents; meshes use one uniform scale),
     theta_deg (yaw), shift (x, y and centre height). Every light_NAME_position default
     is jittered per image by light_jitter metres on each axis. Edit anything else
     (lights, floor, walls, materials, samples) to change the benchmark. -->
<scene version="3.0.0">
    <default name="object" value="{'mug' if name == 'ood' else 'sphere'}" />
    <default name="material" value="rubber" />
    <default name="colour" value="0.417885, 0.0168, 0.0168" />
    <default name="scale" value="0.035, 0.035, 0.035" />
    <default name="theta_deg" value="0" />
    <default name="shift" value="0, 0, 0.035" />"""]
    for light, position, _ in lights:
        out.append(f'    <default name="light_{light}_position" value="{", ".join(map(str, position))}" />')
    out.append(f"""    <default name="light_jitter" value="{LIGHT_JITTER}" />
    <default name="spp" value="128" />
    <default name="width" value="640" />
    <default name="height" value="480" />

    <integrator type="path">
        <integer name="max_depth" value="5" />
    </integrator>
    <sensor type="perspective">
        <float name="fov" value="42.5" />
        <string name="fov_axis" value="y" />
        <transform name="to_world">
            <lookat origin="0, -0.5, 0.35" target="0, 0, 0" up="0, 0, 1" />
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp" />
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="$width" />
            <integer name="height" value="$height" />
            <rfilter type="box" />
        </film>
    </sensor>
""")
    for light, _, radiance in lights:
        value = ", ".join(f"{strength * v:g}" for v in radiance)
        out.append(f"""    <shape type="rectangle" id="light_{light}">
        <transform name="to_world">
            <scale value="{LIGHT_HALF_SIZE}" />
            <lookat origin="$light_{light}_position" target="0, 0, 0.02" up="0, 0, 1" />
        </transform>
        <emitter type="area">
            <rgb name="radiance" value="{value}" />
        </emitter>
    </shape>""")
    out.append(f"""    <shape type="rectangle" id="light_sky">
        <transform name="to_world">
            <scale value="0.6" /><rotate x="1" angle="180" /><translate value="0, 0, 1.2" />
        </transform>
        <emitter type="area">
            <rgb name="radiance" value="{strength * SKY:g}" />
        </emitter>
    </shape>
""")
    if name == "room":
        out.append(f"""    <shape type="rectangle" id="floor">
        <transform name="to_world"><scale value="2" /></transform>
        {_bsdf_diffuse(texture="textures/wood.png", uv_scale=4)}
    </shape>
    <shape type="rectangle" id="back-wall">
        <transform name="to_world">
            <scale value="2, 0.6, 1" /><rotate x="1" angle="90" /><translate value="0, 0.45, 0.6" />
        </transform>
        {_bsdf_diffuse(texture="textures/tiles.png", uv_scale=6)}
    </shape>
    <shape type="rectangle" id="side-wall">
        <transform name="to_world">
            <scale value="2, 0.6, 1" /><rotate x="1" angle="90" /><rotate z="1" angle="90" />
            <translate value="-0.5, 0, 0.6" />
        </transform>
        {_bsdf_diffuse(colour="0.55, 0.32, 0.25")}
    </shape>
""")
    else:
        out.append(f"""    <shape type="rectangle" id="floor">
        <transform name="to_world"><scale value="2" /></transform>
        {_bsdf_diffuse(colour="0.3, 0.3, 0.3")}
    </shape>
""")
    out.append("""    <!-- CLEVR's materials: rubber is a rough plastic, metal a rough conductor tinted by the colour. -->
    <bsdf type="roughplastic" id="rubber">
        <rgb name="diffuse_reflectance" value="$colour" />
        <float name="alpha" value="0.3" />
    </bsdf>
    <bsdf type="roughconductor" id="metal">
        <string name="material" value="none" />
        <rgb name="specular_reflectance" value="$colour" />
        <float name="alpha" value="0.12" />
    </bsdf>

    <!-- Shape groups in the unit frame: centred at the origin, spanning [-1, 1]. -->""")
    if name == "ood":
        for mesh in MESH_NAMES:
            out.append(f"""    <shape type="shapegroup" id="{mesh}">
        <shape type="ply">
            <string name="filename" value="meshes/{mesh}.ply" />
            <boolean name="face_normals" value="true" />
            <ref id="$material" />
        </shape>
    </shape>""")
    else:
        out.append("""    <shape type="shapegroup" id="sphere">
        <shape type="sphere"><ref id="$material" /></shape>
    </shape>
    <shape type="shapegroup" id="cube">
        <shape type="cube"><ref id="$material" /></shape>
    </shape>
    <shape type="shapegroup" id="cylinder">
        <shape type="cylinder">
            <point name="p0" value="0, 0, -1" /><point name="p1" value="0, 0, 1" />
            <ref id="$material" />
        </shape>
        <shape type="disk">
            <transform name="to_world"><translate value="0, 0, 1" /></transform>
            <ref id="$material" />
        </shape>
        <shape type="disk">
            <transform name="to_world"><scale value="1, 1, -1" /><translate value="0, 0, -1" /></transform>
            <ref id="$material" />
        </shape>
    </shape>""")
    out.append("""
    <shape type="instance" id="object">
        <ref id="$object" />
        <transform name="to_world">
            <scale value="$scale" />
            <rotate z="1" angle="$theta_deg" />
            <translate value="$shift" />
        </transform>
    </shape>
</scene>
""")
    return "\n".join(out)


def write_worlds(scenes: Path) -> list[Path]:
    """scenes/benchmarks/*.xml with their textures and meshes."""
    from mitsuba_p3.benchmarks.meshes import write_meshes
    from mitsuba_p3.images import write_png

    folder = scenes / "benchmarks"
    write_png(folder / "textures" / "wood.png", wood_pattern(256))
    write_png(folder / "textures" / "tiles.png", plank_tiles())
    paths = write_meshes(folder / "meshes")
    for name in ("fsclvr", "dark", "room", "ood"):
        path = folder / f"{name}.xml"
        path.write_text(world_xml(name))
        paths.append(path)
    return paths


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "scenes"))
    args = parser.parse_args()
    for name in ("fsclvr", "dark", "room", "ood"):
        scene, description = variant(name)
        path = save_scene(scene, Path(args.out) / f"{name}.xml", description)
        print(path)
    for path in write_worlds(Path(args.out)):
        print(path)


if __name__ == "__main__":
    main()
