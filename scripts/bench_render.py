"""Benchmark the renderers; prints one JSON document.

Figures (median over repeats, milliseconds): one render and a batch of 20 at
120x160 and 480x640 (per image, and images/s), the first call of a fresh
renderer (kernel compilation; Dr.Jit may serve it from its on-disk kernel
cache, which the report says), and forward+backward (render + VJP) at 120x160.
Every timed render changes the object's pose and material, as MCMC does.

    python scripts/bench_render.py [--repeats 50] [--renderers mitsuba,jax]
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
    import drjit as dr

    from mitsuba_p3.render import make_renderer

    rng = np.random.default_rng(0)
    out: dict = {}
    for height, width in ((120, 160), (480, 640)):
        tag = f"{height}x{width}"
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        dr.kernel_history_clear()
        start = time.perf_counter()
        renderer = make_renderer(scene, kind, height=height, width=width)
        renderer.render(_object_params(rng))
        first = 1e3 * (time.perf_counter() - start)
        history = dr.kernel_history()
        dr.set_flag(dr.JitFlag.KernelHistory, False)
        jit = [k for k in history if str(k["type"]).endswith("JIT")]
        out[f"first_call_ms_{tag}"] = round(first, 2)
        if kind == "mitsuba":  # Dr.Jit's kernel cache; JAX compiles in the first call
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
    # hard shadows (the fitted likelihood renders with them), side by side at the inference size
    per_image = {}
    for shadows in (False, True):
        renderer = make_renderer(scene, kind, height=120, width=160, shadows=shadows)
        renderer.render(_object_params(rng, BATCH))
        per_image[shadows] = _median_ms(lambda: renderer.render(_object_params(rng, BATCH)), repeats) / BATCH
    out["batch20_ms_per_image_120x160_shadows_off"] = round(per_image[False], 3)
    out["batch20_ms_per_image_120x160_shadows_on"] = round(per_image[True], 3)
    out["shadows_cost_ratio_120x160"] = round(per_image[True] / per_image[False], 2)
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=50)
    parser.add_argument("--renderers", default="mitsuba,jax", help="comma-separated renderer names")
    parser.add_argument("--scene", default=str(ROOT / "scenes" / "fsclvr.xml"))
    args = parser.parse_args()

    from mitsuba_p3.backend import describe
    from mitsuba_p3.scene import load_scene

    scene = load_scene(args.scene)
    report = {"machine": describe(), "scene": str(Path(args.scene).relative_to(ROOT)), "batch": BATCH,
              "repeats": args.repeats,
              "targets": {"mitsuba": {"single_ms_120x160": 1.5, "single_ms_480x640": 12.0,
                                      "forward_backward_ms_120x160": 6.0, "batch_images_per_s_120x160": 1000},
                          "jax": {"single_ms_120x160": 2.0, "batch_ms_per_image_120x160": "<= single"}},
              "paper_jax_tracer_ms_on_this_machine": {"single_120x160": 3.5, "single_480x640": 101.0,
                                                      "forward_backward_120x160": 10.6}}
    for kind in args.renderers.split(","):
        report[kind] = bench(kind, scene, args.repeats)
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
