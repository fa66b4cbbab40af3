"""Scores in chunks against scores of the whole batch: a posterior's CPU seconds and its draws.

Samples the default P3 posterior of each image twice, each time in a fresh process set up as one of
``evaluate --jobs 2``'s workers (one Dr.Jit thread, a single-threaded XLA): once with the per-particle
scores vmapped over the whole batch (``MITSUBA_P3_JAX_BATCHING=vmap``, the rule a GPU gets and the
sampler's only way before :mod:`mitsuba_p3.infer.chunks`) and once in the CPU's chunks (the default).
Prints per image the process's CPU seconds under each (which another process on the cores delays
but does not inflate) and, after the first image (which also compiles), their ratio; then the largest
difference of the shape probabilities (the draws' mean), of the position draws and of the colour draws' means. The
chunks run the same program on fewer renders at a time, so the draws are either equal to float32
rounding or, once a rounding difference flips one acceptance, as different as another seed's
(docs/notebook.md, "Scores in chunks that fit the cache").

    python experiments/probe_chunked_scores.py data/models/fsclvr-tinted data/fsclvr-lo/test/*/2.png

``--scores`` times the shading fields' score alone (the model's default form) on a synthetic batch of
1,536 renders of 56 x 72 and 4,096 of 28 x 36 (the sampler's two sizes), vmapped whole and in chunks
of 4 to 64 renders, in this process with a single-threaded XLA: CPU microseconds per render.
"""
from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_SAMPLE = """
import json, resource, sys, time, numpy as np
from mitsuba_p3.evaluate.jobs import _limit_threads
_limit_threads(1)
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.images import read_png
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.posterior import default_likelihood, infer_image
from mitsuba_p3.infer.smc import SMCConfig
def cpu():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime
fitted = FittedModel(sys.argv[2])
likelihood = default_likelihood(fitted, "p3", noise=DEFAULT_NOISE)
out, seconds = {}, []
for i, path in enumerate(sys.argv[3:]):
    start, wall = cpu(), time.perf_counter()
    posterior = infer_image(fitted, read_png(path), likelihood, SMCConfig()).idata.posterior
    seconds.append([cpu() - start, time.perf_counter() - wall])
    for name in ("class_probabilities", "shift", "colour"):
        out[f"{i}/{name}"] = np.asarray(posterior[name])
np.savez(sys.argv[1], seconds=np.asarray(seconds), **out)
"""


_SCORES = """
import resource, sys, numpy as np
from mitsuba_p3.evaluate.jobs import _limit_threads
_limit_threads(1)
import jax, jax.numpy as jnp
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE, score
from mitsuba_p3.infer.posterior import default_likelihood
def cpu():
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime
config = default_likelihood(FittedModel(sys.argv[1]), "p3", noise=DEFAULT_NOISE)
rng = np.random.default_rng(0)
for batch, (h, w) in ((1536, (56, 72)), (4096, (28, 36))):
    observation = {"image": jnp.asarray(rng.uniform(0, 1, (h, w, 3)), jnp.float32),
                   "empty": jnp.asarray(rng.uniform(0, 1, (h, w, 3)), jnp.float32)}
    renders = jnp.asarray(rng.uniform(0, 1, (batch, h, w, 3)), jnp.float32)
    objects = jnp.asarray(rng.uniform(0, 1, (batch, h, w)) < 0.2)
    colours = jnp.asarray(rng.uniform(0.1, 0.9, (batch, 3)), jnp.float32)
    one = lambda r, o, c: score(observation, r[None], config, [], o[None], c[None])[0]
    runs = [("whole", jax.jit(jax.vmap(one)))] + [
        (f"chunks of {n}", jax.jit(lambda r, o, c, n=n: jax.lax.map(lambda a: one(*a), (r, o, c), batch_size=n)))
        for n in (4, 8, 16, 32, 64)]
    for name, f in runs:
        f(renders, objects, colours).block_until_ready()
        start = cpu()
        for _ in range(5):
            f(renders, objects, colours).block_until_ready()
        print(f"{batch} renders of {h} x {w}, {name}: {(cpu() - start) / 5 / batch * 1e6:.1f} us CPU per render", flush=True)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="a fitted-model folder (mitsuba-p3 fit)")
    parser.add_argument("images", type=Path, nargs="*", help="images at the model's resolution")
    parser.add_argument("--json", type=Path, help="also write the figures here")
    parser.add_argument("--scores", action="store_true", help="first time the score alone (the module docstring)")
    args = parser.parse_args()
    if args.scores:
        subprocess.run([sys.executable, "-c", _SCORES, str(args.model)], check=True)
    if not args.images:
        return
    folder = Path(tempfile.mkdtemp(prefix="probe-chunks-"))
    runs = {}
    for name, batching in (("whole", "vmap"), ("chunks", "")):
        env = dict(os.environ, MITSUBA_P3_JAX_BATCHING=batching)
        out = folder / f"{name}.npz"
        subprocess.run([sys.executable, "-c", _SAMPLE, str(out), str(args.model), *map(str, args.images)],
                       env=env, check=True)
        runs[name] = np.load(out)
    a, b = runs["whole"], runs["chunks"]
    rows = []
    for i, path in enumerate(args.images):
        # the posterior's shape probabilities: the draws' class probabilities averaged (a draw's own is 0 or 1
        # where its run's hypothesis decides it, so draws that differ differ there by 1)
        mean = lambda run: run[f"{i}/class_probabilities"].reshape(-1, 3).mean(axis=0)  # noqa: E731
        shape = float(np.abs(mean(a) - mean(b)).max())
        shift = float(np.abs(a[f"{i}/shift"] - b[f"{i}/shift"]).max())
        colour = float(np.abs(a[f"{i}/colour"].mean(axis=(0, 1)) - b[f"{i}/colour"].mean(axis=(0, 1))).max())
        (cpu_a, wall_a), (cpu_b, wall_b) = a["seconds"][i], b["seconds"][i]
        rows.append({"image": str(path), "cpu_whole": float(cpu_a), "cpu_chunks": float(cpu_b),
                     "wall_whole": float(wall_a), "wall_chunks": float(wall_b), "shape_probabilities": shape,
                     "position_draws": shift, "colour_means": colour})
        print(f"{path}: CPU {cpu_a:.1f} s whole, {cpu_b:.1f} s in chunks{' (with compilation)' if i == 0 else ''}; "
              f"shape probabilities {shape:.2g}, position draws {shift:.2g}, colour means {colour:.2g}", flush=True)
    steady = rows[1:]
    if steady:
        whole, chunks = sum(r["cpu_whole"] for r in steady), sum(r["cpu_chunks"] for r in steady)
        print(f"after the first image: CPU {whole:.1f} s whole, {chunks:.1f} s in chunks, ratio {chunks / whole:.2f} "
              f"({len(steady)} posteriors; {whole / len(steady):.1f} -> {chunks / len(steady):.1f} s each)")
    if args.json:
        args.json.write_text(json.dumps({"images": rows}, indent=1))


if __name__ == "__main__":
    main()
