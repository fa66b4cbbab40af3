"""Benchmark the renderers; prints one JSON document.

Figures (median over repeats, milliseconds): one render and a batch of 20 at
120x160 and 480x640 (per image, and images/s), the first call of a fresh
renderer (kernel compilation; Dr.Jit may serve it from its on-disk kernel
cache, which the report says), and forward+backward (render + VJP) at 120x160.
Every timed render changes the object's pose and material, as MCMC does.
``--wide 256,4096`` adds the JAX tracer's wide batches at 120x160 with both
batchings (``map``: one image after another, the CPU's default; ``vmap``: one
launch, the GPU's default), each with the images copied to the host (``render``)
and kept on the device (``render_jax`` under jit). ``--callbacks 128,512`` adds Mitsuba inside
JAX as the SMC calls it (``jit(vmap(...))`` of the 56x72 scoring window with the object's pixels,
image and material bases) through ``jax.pure_callback`` (numpy images copied into XLA) and in place
(``buffer_callback``: Dr.Jit renders into XLA's buffers), interleaved, and which one is the default
here (:func:`mitsuba_p3.infer.render_functions.mitsuba_render_function`). The report starts with where
it ran (variant, CPU cores, GPU, JAX's backend); without Mitsuba installed (a GPU
machine with JAX only) ``--renderers jax`` still runs.

    python scripts/bench_render.py [--repeats 50] [--renderers mitsuba,jax] [--wide 256,4096] [--callbacks 128,512]
"""
from __future__ import annotations

import argparse
import json
import statistics
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BATCH = 20


def _object_params(rng, batch=None):
    shape = () if batch is None else (batch,)
    return {
        "shift": rng.uniform(-0.06, 0.06, (*shape, 2)).astype(np.float32),
        "theta": rng.uniform(-np.pi, np.pi, shape).astype(np.float32),
        "scale": rng.uniform(0.015, 0.04, (*shape, 3)).astype(np.float32),
        "kappa": rng.integers(0, 3, shape).astype(np.int32),
        "colour": rng.uniform(0.1, 0.9, (*shape, 3)).astype(np.float32),
        "shininess": rng.uniform(2, 40, shape).astype(np.float32),
    }


def _median_ms(fn, repeats: int) -> float:
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return 1e3 * statistics.median(times)


def bench(kind: str, scene, repeats: int) -> dict:
    from mitsuba_p3.render import make_renderer

    if kind == "mitsuba":
        import drjit as dr
    else:
        dr = None

    rng = np.random.default_rng(0)
    out: dict = {}
    for height, width in ((120, 160), (480, 640)):
        tag = f"{height}x{width}"
        if dr is not None:
            dr.set_flag(dr.JitFlag.KernelHistory, True)
            dr.kernel_history_clear()
        start = time.perf_counter()
        renderer = make_renderer(scene, kind, height=height, width=width)
        renderer.render(_object_params(rng))
        first = 1e3 * (time.perf_counter() - start)
        out[f"first_call_ms_{tag}"] = round(first, 2)
        if dr is not None:  # Dr.Jit's kernel cache; JAX compiles in the first call
            history = dr.kernel_history()
            dr.set_flag(dr.JitFlag.KernelHistory, False)
            jit = [k for k in history if str(k["type"]).endswith("JIT")]
            out[f"first_call_kernels_compiled_{tag}"] = sum(
                1 for k in jit if not k["cache_hit"] and not k.get("cache_disk"))
            out[f"first_call_kernels_from_disk_cache_{tag}"] = sum(1 for k in jit if k.get("cache_disk"))
        renderer.render(_object_params(rng, BATCH))  # compile the batched kernel
        single = _median_ms(lambda: renderer.render(_object_params(rng)), repeats)
        batch = _median_ms(lambda: renderer.render(_object_params(rng, BATCH)), max(5, repeats // 5))
        out[f"single_ms_{tag}"] = round(single, 3)
        out[f"batch{BATCH}_ms_per_image_{tag}"] = round(batch / BATCH, 3)
        out[f"batch{BATCH}_images_per_s_{tag}"] = round(1e3 * BATCH / batch, 1)
        out[f"batch_speedup_vs_single_{tag}"] = round(single / (batch / BATCH), 2)
        if height == 120:
            cotangent = np.ones((height, width, 3), np.float32)
            renderer.vjp(_object_params(rng), cotangent)
            out[f"forward_backward_ms_{tag}"] = round(
                _median_ms(lambda: renderer.vjp(_object_params(rng), cotangent), repeats), 3)
    # shadows off, hard, and soft (lights of 3 cm radius, SOFT_SHADOW_SAMPLES points each), side by
    # side at the inference size
    from mitsuba_p3.render.soft_shadows import SOFT_SHADOW_SAMPLES

    per_image = {}
    for name, shadows, radius in (("off", False, 0.0), ("on", True, 0.0), ("soft", True, 0.03)):
        renderer = make_renderer(scene.replace(light_radius=radius), kind, height=120, width=160, shadows=shadows)
        renderer.render(_object_params(rng, BATCH))
        per_image[name] = _median_ms(lambda: renderer.render(_object_params(rng, BATCH)), repeats) / BATCH
        out[f"batch20_ms_per_image_120x160_shadows_{name}"] = round(per_image[name], 3)
    out["shadows_cost_ratio_120x160"] = round(per_image["on"] / per_image["off"], 2)
    out["soft_shadows_samples"] = SOFT_SHADOW_SAMPLES
    out["soft_shadows_cost_ratio_vs_hard_120x160"] = round(per_image["soft"] / per_image["on"], 2)
    return out


def bench_wide(scene, batches: list[int], repeats: int) -> dict:
    """The JAX tracer's wide batches at 120x160, both batchings, host copies and not (images/s)."""
    import os

    import jax
    import jax.numpy as jnp

    from mitsuba_p3.render.jax_tracer import BATCHING_ENV, JaxRenderer

    rng = np.random.default_rng(1)
    out: dict = {}
    forced = os.environ.get(BATCHING_ENV)
    try:
        for mode in ("map", "vmap"):
            os.environ[BATCHING_ENV] = mode
            renderer = JaxRenderer(scene, height=120, width=160)
            on_device = jax.jit(renderer.render_jax)
            for batch in batches:
                params = [_object_params(rng, batch) for _ in range(2)]
                device = [{k: jnp.asarray(v) for k, v in renderer.merged(p).items()} for p in params]
                renderer.render(params[0])
                on_device(device[0]).block_until_ready()
                count = max(3, repeats // 10)
                host = _median_ms(lambda: renderer.render(params[1]), count)
                kept = _median_ms(lambda: on_device(device[1]).block_until_ready(), count)
                out[f"{mode}_batch{batch}_images_per_s_host_copy"] = round(1e3 * batch / host, 1)
                out[f"{mode}_batch{batch}_images_per_s_on_device"] = round(1e3 * batch / kept, 1)
    finally:
        if forced is None:
            os.environ.pop(BATCHING_ENV, None)
        else:
            os.environ[BATCHING_ENV] = forced
    from mitsuba_p3.render.jax_tracer import batching_for

    out["default_batching_here"] = batching_for()
    return out


def bench_callbacks(scene, batches: list[int], repeats: int) -> dict:
    """Mitsuba inside JAX, the SMC's windowed call, through pure_callback and in place (ms per call)."""
    import jax
    import jax.numpy as jnp

    from mitsuba_p3.infer.render_functions import in_place_available, mitsuba_render_function
    from mitsuba_p3.render import make_renderer
    from mitsuba_p3.space import OBJECT_KEYS

    renderer = make_renderer(scene, "mitsuba", height=120, width=160)
    out: dict = {"in_place_available": in_place_available(), "default_in_place_here": bool(
        renderer.on_device and in_place_available())}
    if not in_place_available():
        return out
    rng = np.random.default_rng(2)
    offset = jnp.array([30, 40], jnp.int32)
    for bases in (False, True):
        calls = {way: jax.jit(jax.vmap(lambda p, f=mitsuba_render_function(renderer, bases, (56, 72), True, in_place=way):
                                       f(p, offset)))
                 for way in (False, True)}
        for batch in batches:
            params = {k: jnp.asarray(v) for k, v in renderer.merged(_object_params(rng, batch)).items()
                      if k in OBJECT_KEYS}
            times: dict = {False: [], True: []}
            for call in calls.values():
                jax.block_until_ready(call(params))
            for _ in range(max(5, repeats // 5)):
                for way, call in calls.items():         # interleaved: both see the same machine
                    start = time.perf_counter()
                    jax.block_until_ready(call(params))
                    times[way].append(time.perf_counter() - start)
            tag = f"{'bases' if bases else 'image'}_batch{batch}"
            pure, in_place = (1e3 * statistics.median(times[w]) for w in (False, True))
            out[f"{tag}_ms_pure_callback"] = round(pure, 3)
            out[f"{tag}_ms_in_place"] = round(in_place, 3)
            out[f"{tag}_in_place_over_pure"] = round(in_place / pure, 3)
    return out


def where() -> dict:
    """Where this ran: the Mitsuba variant (when Mitsuba is installed), CPU cores, GPU, JAX's backend."""
    from mitsuba_p3 import backend

    try:
        return backend.describe()
    except Exception as exc:  # a GPU machine with JAX but no Mitsuba wheel
        import os

        return {"mitsuba": f"unavailable ({exc})", "cpu_cores": os.cpu_count(), **backend.gpu()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--renderers", default="mitsuba,jax", help="comma-separated renderer names ('' for none)")
    parser.add_argument("--scene", default=str(ROOT / "scenes" / "fsclvr.xml"))
    parser.add_argument("--wide", default="", help="comma-separated wide batch sizes for the JAX tracer")
    parser.add_argument("--callbacks", default="", help="comma-separated batch sizes: Mitsuba inside JAX, "
                                                         "pure_callback against in place")
    args = parser.parse_args()

    from mitsuba_p3.scene import load_scene

    scene = load_scene(args.scene)
    report = {"machine": where(), "scene": str(Path(args.scene).relative_to(ROOT)), "batch": BATCH,
              "repeats": args.repeats,
              "targets": {"mitsuba": {"single_ms_120x160": 1.5, "single_ms_480x640": 12.0,
                                      "forward_backward_ms_120x160": 6.0, "batch_images_per_s_120x160": 1000},
                          "jax": {"single_ms_120x160": 2.0, "batch_ms_per_image_120x160": "<= single"}},
              "paper_jax_tracer_ms_on_this_machine": {"single_120x160": 3.5, "single_480x640": 101.0,
                                                      "forward_backward_120x160": 10.6}}
    for kind in filter(None, args.renderers.split(",")):
        report[kind] = bench(kind, scene, args.repeats)
    if args.wide:
        report["jax_wide_120x160"] = bench_wide(scene, [int(b) for b in args.wide.split(",")], args.repeats)
    if args.callbacks:
        report["mitsuba_in_jax_window_56x72"] = bench_callbacks(scene, [int(b) for b in args.callbacks.split(",")],
                                                                args.repeats)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
