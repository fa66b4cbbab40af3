"""Seconds per P3 posterior, in one process, after a warm-up: what one image costs where this runs.

For each particle count, the first image is sampled once to compile (not timed), then every image
is sampled and timed; prints the machine (variant, CPU cores, GPU, JAX's backend) and, per particle
count, the median and each image's seconds, modal shape and the island gap. ``--truth`` (a JSON
list of {"class": {"shape": ...}}) adds the share of right shapes; ``--set smc.FIELD=VALUE`` changes the
sampler as on ``mitsuba-p3 infer``; ``--profile FILE`` writes where the last image's seconds went
(cProfile, the 40 costliest calls by cumulative time); ``--seeds 2`` samples every image under two
seeds and adds the share of images whose decided shape is the same under all of them, with the
island gap's median, 90th percentile and share over 10 nats. ``--steps host,device`` runs every
particle count under each way of running a plain SMC step (``MITSUBA_P3_SMC_STEP``: on the host, or
as one compiled call on the device, :mod:`mitsuba_p3.infer.device_step`), side by side in one process.

    python scripts/bench_posterior.py MODEL IMAGE... [--renderer jax] [--particles 64,256] [--truth T]
                                      [--steps host,device]
"""
import argparse
import json
import os
import statistics
import time
from dataclasses import replace

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model")
    parser.add_argument("images", nargs="+")
    parser.add_argument("--renderer", default="jax", help="jax (no callback) or mitsuba")
    parser.add_argument("--particles", default="64", help="comma-separated SMC particles per hypothesis")
    parser.add_argument("--truth", default=None)
    parser.add_argument("--set", dest="settings", action="append", default=[], help="smc.FIELD=VALUE")
    parser.add_argument("--profile", default=None, help="write the last image's profile here")
    parser.add_argument("--seeds", type=int, default=1, help="sample every image under this many seeds")
    parser.add_argument("--noise", default=None, help="the noise form (default: the default, DEFAULT_NOISE)")
    parser.add_argument("--steps", default=None, help="comma-separated: host, device (default: the device's choice)")
    args = parser.parse_args()
    from mitsuba_p3.cli.settings import apply_settings
    from mitsuba_p3.fit.model import FittedModel
    from mitsuba_p3.images import load_observation
    from mitsuba_p3.infer.device_step import STEP_ENV, STEPS, step_for
    from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
    from mitsuba_p3.infer.posterior import default_likelihood, sample_posterior
    from mitsuba_p3.infer.smc import SMCConfig
    from bench_render import where

    steps = args.steps.split(",") if args.steps else [step_for()]
    if any(step not in STEPS for step in steps):
        parser.error(f"--steps: each one of {', '.join(STEPS)}")
    fitted = FittedModel(args.model)
    noise = args.noise or DEFAULT_NOISE
    likelihood = default_likelihood(fitted, "p3", None, noise)
    images = [load_observation(p) for p in args.images]
    truth = [t["class"]["shape"] for t in json.load(open(args.truth))] if args.truth else None
    report = {"machine": where(), "renderer": args.renderer, "noise": noise, "images": len(images),
              "settings": args.settings, "runs": {}}
    for step, particles in ((s, int(p)) for p in args.particles.split(",") for s in steps):
        os.environ[STEP_ENV] = step
        name = f"{particles} {step}" if args.steps else particles
        config = apply_settings(SMCConfig(particles=particles), args.settings)
        start = time.perf_counter()
        try:
            sample_posterior(fitted, images[0], likelihood, config, renderer=args.renderer)
        except Exception as error:       # e.g. out of device memory: say so and go on with the next count
            report["runs"][name] = {"failed": f"{type(error).__name__}: {str(error)[:200]}"}
            print(json.dumps({name: report["runs"][name]}), flush=True)
            continue
        warm = time.perf_counter() - start
        rows = []
        for number, (seed, image) in enumerate((s, i) for s in range(args.seeds) for i in images):
            profile = None
            if args.profile and number == len(images) - 1:
                import cProfile

                profile = cProfile.Profile()
                profile.enable()
            start = time.perf_counter()
            posterior = sample_posterior(fitted, image, likelihood, replace(config, seed=config.seed + seed),
                                    renderer=args.renderer)
            if profile is not None:
                import pstats

                profile.disable()
                with open(args.profile, "a") as stream:
                    stream.write(f"== {particles} particles per hypothesis, the {step} step\n")
                    pstats.Stats(profile, stream=stream).sort_stats("cumulative").print_stats(40)
            rows.append({"seed": seed, "seconds": round(time.perf_counter() - start, 3),
                         "shape": posterior.estimate()["shape"], "island_gap": posterior.statistic("island_gap")})
        entry = {"step": step, "first_call_seconds": round(warm, 2),
                 "median_seconds": round(statistics.median(r["seconds"] for r in rows), 3), "per_image": rows}
        gaps = np.array([r["island_gap"] for r in rows], float)
        entry["island_gap"] = {"median": float(np.nanmedian(gaps)), "p90": float(np.nanpercentile(gaps, 90)),
                               "over_10": float(np.nanmean(gaps > 10))}
        if args.seeds > 1:       # the decided shape of each image under every seed
            shapes = np.array([r["shape"] for r in rows]).reshape(args.seeds, len(images))
            entry["same_shape_every_seed"] = float(np.mean(np.all(shapes == shapes[:1], axis=0)))
        if truth:
            entry["shape_right"] = float(np.mean([r["shape"] == truth[n % len(images)] for n, r in enumerate(rows)]))
        report["runs"][name] = entry
        print(json.dumps({name: {k: v for k, v in entry.items() if k != "per_image"}}), flush=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
