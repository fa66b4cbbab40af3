"""Write the Phong scene of each benchmark variant, and the textures and meshes of the worlds.

- scenes/VARIANT.xml: the Phong model's scene (phong_integrator), regenerated from the values below;
- scenes/benchmarks/{textures,meshes}/: what the path-traced worlds reference.

The path-traced worlds themselves, scenes/benchmarks/VARIANT.xml (what `mitsuba-p3
benchmark generate` renders), are edited as XML and never written by this
script: copy one to make a new benchmark. Usage:

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


# ---------------------------------------------------------------- textures of the path-traced worlds

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


def write_world_assets(scenes: Path) -> list[Path]:
    """The textures and meshes that the benchmark worlds (scenes/benchmarks/*.xml) reference."""
    from mitsuba_p3.benchmarks.meshes import write_meshes
    from mitsuba_p3.images import write_png

    folder = scenes / "benchmarks"
    write_png(folder / "textures" / "wood.png", wood_pattern(256))
    write_png(folder / "textures" / "tiles.png", plank_tiles())
    return write_meshes(folder / "meshes")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(Path(__file__).resolve().parents[1] / "scenes"))
    args = parser.parse_args()
    for name in ("fsclvr", "dark", "room", "ood"):
        scene, description = variant(name)
        path = save_scene(scene, Path(args.out) / f"{name}.xml", description)
        print(path)
    for path in write_world_assets(Path(args.out)):
        print(path)


if __name__ == "__main__":
    main()
