"""Inference benchmark: seconds per test image, ESS per second and R-hat, for both renderers.

Runs `infer_image` at the default settings (np3 likelihood, the default SamplerConfig)
on one fixed fsclvr test image, once with Mitsuba (pure_callback) and once with the
JAX tracer, and prints JSON. Needs a benchmark folder and a model fitted to it:

    mitsuba-p3 benchmark generate fsclvr --out data/fsclvr
    mitsuba-p3 fit data/fsclvr --out data/models/fsclvr
    python scripts/bench_infer.py [--dataset data/fsclvr] [--model data/models/fsclvr] [--image-index 0]

Targets (issue 6): R-hat <= 1.05 and ESS >= 400 for shift, scale and colour in <= 30 s.
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.mcmc import SamplerConfig
from mitsuba_p3.infer.posterior import default_likelihood, infer_image

TARGET_VARIABLES = ("shift", "scale", "colour")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--image-index", type=int, default=0, help="index among the test images")
    parser.add_argument("--likelihood", default="np3")
    parser.add_argument("--renderers", default="mitsuba,jax")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    shot = dataset.split("test")[args.image_index]
    fitted = FittedModel(args.model)
    observed = dataset.image(shot)
    config = SamplerConfig()
    results = {"image": str(shot.file), "truth": {"shape": shot.cls.shape, "shift": shot.position[:2].tolist(),
                                                  "scale": shot.scale.tolist()},
               "sampler": {k: v for k, v in vars(config).items()}, "likelihood": args.likelihood, "runs": {}}
    for renderer in args.renderers.split(","):
        # a short run first, so that compilation is not timed
        infer_image(fitted, observed, default_likelihood(fitted, args.likelihood),
                    SamplerConfig(chains=config.chains, steps=config.block, burn_in=0, tune_rounds=1,
                                  tune_steps=config.block, init_candidates=config.init_candidates),
                    renderer=renderer)
        start = time.perf_counter()
        posterior = infer_image(fitted, observed, default_likelihood(fitted, args.likelihood), config,
                                renderer=renderer)
        seconds = time.perf_counter() - start
        summary = posterior.summary()
        estimate = posterior.estimate()
        targeted = summary[[any(i.startswith(v) for v in TARGET_VARIABLES) for i in summary.index]]
        results["runs"][renderer] = {
            "seconds": round(seconds, 2),
            "acceptance": round(float(posterior.idata.sample_stats["accepted"].values.mean()), 3),
            "ess_bulk": {k: round(float(v), 1) for k, v in summary["ess_bulk"].items()},
            "ess_per_second": {k: round(float(v) / seconds, 2) for k, v in summary["ess_bulk"].items()},
            "max_r_hat_targeted": round(float(targeted["r_hat"].max()), 3),
            "min_ess_targeted": round(float(targeted["ess_bulk"].min()), 1),
            "max_r_hat_all": round(float(summary["r_hat"].max()), 3),
            "estimate": {"shape": estimate["shape"], "shift": np.round(estimate["shift"], 4).tolist(),
                         "scale": np.round(estimate["scale"], 4).tolist(),
                         "class_frequencies": estimate["class_frequencies"]},
        }
        print(json.dumps({renderer: results["runs"][renderer]}), flush=True)
    print(json.dumps(results, indent=1))


if __name__ == "__main__":
    main()
