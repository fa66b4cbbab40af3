"""Where a noise form's seconds go: one batched likelihood evaluation, and how many temperatures a run takes.

A posterior's cost is (likelihood evaluations per temperature) x (temperatures). For each noise form of
``--noises`` this times, on one train image's scoring window and ``--batch`` prior draws, the parts of one
batched evaluation as the sampler compiles them (the render through Mitsuba's callback, the traced object
pixels the shading fields need, the density), each the mean of 5 calls after one warm-up call; then samples
the default SMC on ``--images`` evenly spaced train images and prints each run's seconds and number of
temperatures (the largest over its hypotheses' runs: the adaptive tempering takes more steps when the
likelihood holds more information, so a sharper form pays twice). No test image is used.

    python experiments/likelihood_cost.py --dataset data/jitter-lo --model data/models/jitter-lo \\
        --noises fitted,fields --images 2
"""
from __future__ import annotations

import argparse
import json
import time

import jax
import jax.numpy as jnp
import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.likelihood import score
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.smc import SMCConfig, sample_smc


def seconds(function, *args, calls: int = 5) -> float:
    """Mean seconds of ``calls`` calls after one (compiling) call."""
    jax.block_until_ready(function(*args))
    start = time.perf_counter()
    for _ in range(calls):
        jax.block_until_ready(function(*args))
    return (time.perf_counter() - start) / calls


def parts(core: PosteriorCore, observation: dict, batch: int) -> dict:
    """Seconds of one batched evaluation and of its parts, on ``batch`` prior draws."""
    z = jnp.asarray(core.prior.sample(np.random.default_rng(0), batch), jnp.float32)
    render = jax.jit(jax.vmap(lambda p: core._image(p, observation)))
    total = jax.jit(jax.vmap(lambda p: core.log_likelihood(p, observation)))
    images, covered = render(z)
    out = {"render": seconds(render, z)}
    if core.config.fields is not None:
        objects = jax.jit(jax.vmap(lambda p: core.objects(p, observation)))
        out["object_pixels"] = seconds(objects, z)   # the JAX tracer's (Mitsuba's come with its render)
        colours = core.params(z)["colour"]       # (tinted fields load on them)
        density = jax.jit(lambda r, o: score(observation, r, core.config, None, o, colours))
        out["density"] = seconds(density, images, covered)
    else:
        out["density"] = seconds(jax.jit(lambda r: score(observation, r, core.config, None)), images)
    out["evaluation"] = seconds(total, z)
    return {k: round(v, 4) for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", required=True)
    parser.add_argument("--model", required=True)
    parser.add_argument("--noises", default="fitted,fields", help="comma-separated noise forms")
    parser.add_argument("--images", type=int, default=2, help="evenly spaced train images sampled")
    parser.add_argument("--batch", type=int, default=512, help="draws per timed evaluation (the SMC's first step)")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    shots = dataset.split("train")
    chosen = [shots[int(i)] for i in np.linspace(0, len(shots) - 1, args.images)]
    config = SMCConfig()
    report = {"dataset": args.dataset, "model": args.model, "batch": args.batch, "noises": {}}
    for noise in args.noises.split(","):
        core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=noise), "mitsuba", *dataset.resolution)
        image = dataset.image(chosen[0])
        observation = core.observe(image, core.window_for(image, config.window))
        entry = {"evaluation_seconds": parts(core, observation, args.batch), "runs": []}
        sample_smc(core, core.observe(dataset.image(chosen[0])), SMCConfig(max_temperatures=2))   # compile
        for shot in chosen:
            start = time.perf_counter()
            run = sample_smc(core, core.observe(dataset.image(shot)), config)
            entry["runs"].append({"image": shot.class_name, "seconds": round(time.perf_counter() - start, 1),
                                  "temperatures": int(run.particles.rows.temperatures)})
            print(noise, entry["runs"][-1], flush=True)
        report["noises"][noise] = entry
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
