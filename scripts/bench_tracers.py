"""The project's JAX tracer beside the paper authors' (``tamayo``), side by side in one run.

Both render the fsclvr scene (floor, one object, the scene's three point lights, shadows off as in the
scene file, and on) at 120x160, a batch of random poses, classes and materials per call, batched the
same way (one ``jit(vmap(...))`` launch, arrays kept on the device, ``block_until_ready`` inside the
timed region), after a compiling call; two input sets alternate so no call repeats the last one's
inputs. Prints one JSON document: where it ran, images/s per tracer and batch, and our/authors' ratio.

The authors' tracer is not a dependency: clone it and pass the folder that holds ``tamayo/``::

    git clone https://github.com/oarriaga/bayesian-inverse-graphics authors   # MIT; used at 99a4386
    python scripts/bench_tracers.py --authors authors [--batches 20,256,4096] [--repeats 20]
        [--figure tracers.png]

The scene is carried over to tamayo's frame (its floor is y = 0 with y up; ours z = 0 with z up:
(x, y, z) -> (x, z, -y), a rotation), with the same camera, vertical field of view, lights, floor
and object materials; its canonical shapes span [-1, 1] along each axis, ours are placed by half
extents, so the same transform places both. ``--figure`` writes the first image of each tracer side
by side, to see that both draw the same scene. Only the speed is compared: the images are alike,
not equal (tamayo's camera draws the scene mirrored left to right and its object smaller, it adds the
ambient term once per light, and its cube and cylinder are its own); both tracers shade every pixel,
so the object's size does not change the cost.
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent
sys.path.insert(0, str(ROOT))
HEIGHT, WIDTH = 120, 160
TAMAYO_TYPE = {0: 0, 1: 1, 2: 2}   # our SHAPES order (sphere, cube, cylinder) -> tamayo's type ids
PATTERN = (8, 8, 3)                # tamayo's pattern images (unused: no pattern on either surface)


def _frame(v):
    """Our z-up point or vector as tamayo's y-up one."""
    v = np.asarray(v, np.float32)
    return np.stack([v[..., 0], v[..., 2], -v[..., 1]], -1)


def authors_renderer(scene, tamayo_root: str, shadows: bool):
    """``render(batch) -> images (B, H, W, 3)`` through tamayo's ``Render``, jit(vmap) over the batch."""
    sys.path.insert(0, str(Path(tamayo_root).resolve()))
    import jax
    import jax.numpy as jnp
    from tamayo import SE3, Material, PointLight, Render, Shape, build_rays
    from tamayo.abstract import Pattern

    camera = scene.camera
    pose = SE3.view_transform(jnp.asarray(_frame(camera.origin)), jnp.asarray(_frame(camera.target)),
                              jnp.asarray(_frame(camera.up)))
    origins, directions = build_rays((HEIGHT, WIDTH), np.radians(camera.fov), pose)
    render = Render(origins, directions, HEIGHT, WIDTH, shadows)
    lights = [PointLight(jnp.asarray(light.intensity, jnp.float32), jnp.asarray(_frame(light.position)))
              for light in scene.lights]
    no_pattern = Pattern(jnp.eye(4), 0, jnp.zeros(PATTERN))
    m = scene.floor.material
    floor = Shape(jnp.eye(4), 4, no_pattern, Material(jnp.asarray(m.colour, jnp.float32), m.ambient, m.diffuse,
                                                      m.specular, m.shininess))
    mask = jnp.ones(2, bool)

    def one(obj):
        transform = (SE3.translation(jnp.stack([obj["shift"][0], obj["scale"][2], -obj["shift"][1]]))
                     @ SE3.rotation_y(obj["theta"]) @ SE3.scaling(obj["scale"][jnp.array([0, 2, 1])]))
        shape = Shape(transform, obj["type"], no_pattern,
                      Material(obj["colour"], 0.1, 0.9, 0.1, obj["shininess"]))
        both = jax.tree_util.tree_map(lambda a, b: jnp.stack([jnp.asarray(a), jnp.asarray(b)]), shape, floor)
        image, _depth = render(both, mask, lights)
        return image

    batched = jax.jit(jax.vmap(one))

    def to_device(params):
        return {"shift": jnp.asarray(params["shift"]), "theta": jnp.asarray(params["theta"]),
                "scale": jnp.asarray(params["scale"]), "colour": jnp.asarray(params["colour"]),
                "shininess": jnp.asarray(params["shininess"]),
                "type": jnp.asarray(np.vectorize(TAMAYO_TYPE.get)(params["kappa"]), jnp.int32)}

    return batched, to_device


def ours_renderer(scene, shadows: bool):
    import jax
    import jax.numpy as jnp

    from mitsuba_p3.render.jax_tracer import BATCHING_ENV, JaxRenderer
    import os

    os.environ[BATCHING_ENV] = "vmap"          # one launch, as tamayo's vmap: the same batching on both
    renderer = JaxRenderer(scene.replace(shadows=shadows), height=HEIGHT, width=WIDTH, shadows=shadows)
    batched = jax.jit(renderer.render_jax)

    def to_device(params):
        return {k: jnp.asarray(v) for k, v in renderer.merged(params).items()}

    return batched, to_device


def _median_ms(fn, inputs, repeats: int) -> float:
    times = []
    for n in range(repeats):
        x = inputs[n % len(inputs)]
        start = time.perf_counter()
        fn(x).block_until_ready()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--authors", required=True, help="a folder holding the authors' tamayo/ package")
    parser.add_argument("--batches", default="20,256,4096")
    parser.add_argument("--repeats", type=int, default=20)
    parser.add_argument("--scene", default=str(ROOT.parent / "scenes" / "fsclvr.xml"))
    parser.add_argument("--figure", default=None, help="write both tracers' first image side by side here")
    args = parser.parse_args()
    if not (Path(args.authors) / "tamayo" / "render.py").is_file():
        parser.error(f"{args.authors} holds no tamayo/render.py: clone the authors' repository (see --help)")

    from bench_render import _object_params, where
    from mitsuba_p3.scene import load_scene

    scene = load_scene(args.scene)
    report = {"machine": where(), "scene": Path(args.scene).name, "resolution": [HEIGHT, WIDTH],
              "repeats": args.repeats, "batching": "jit(vmap) on both, arrays on the device", "runs": {}}
    rng = np.random.default_rng(0)
    for shadows in (False, True):
        tracers = {"ours": ours_renderer(scene, shadows), "authors": authors_renderer(scene, args.authors, shadows)}
        for batch in (int(b) for b in args.batches.split(",")):
            params = [_object_params(rng, batch) for _ in range(2)]
            row = {}
            for name, (fn, to_device) in tracers.items():
                inputs = [to_device(p) for p in params]
                start = time.perf_counter()
                first = fn(inputs[0]).block_until_ready()
                row[f"{name}_first_call_s"] = round(time.perf_counter() - start, 2)
                ms = _median_ms(fn, inputs, args.repeats)
                row[f"{name}_images_per_s"] = round(1e3 * batch / ms, 1)
                if args.figure and batch == int(args.batches.split(",")[0]) and not shadows:
                    row.setdefault("_first", {})[name] = np.asarray(first[0])
            row["ours_over_authors"] = round(row["ours_images_per_s"] / row["authors_images_per_s"], 2)
            first_images = row.pop("_first", None)
            if first_images:
                import matplotlib.pyplot as plt

                fig, axes = plt.subplots(1, 2, figsize=(8, 3.2))
                for ax, (name, image) in zip(axes, first_images.items()):
                    ax.imshow(np.clip(image, 0, 1))
                    ax.set_title(f"{name} (shape {int(params[0]['kappa'][0])})")
                    ax.axis("off")
                fig.tight_layout()
                fig.savefig(args.figure, dpi=100)
            key = f"shadows_{'on' if shadows else 'off'}_batch{batch}"
            report["runs"][key] = row
            print(json.dumps({key: row}), flush=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
