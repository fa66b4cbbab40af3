"""Choose the likelihood's noise form on train classes: which one lets the sampler find the object.

The fit stage fits two noise models to the train residuals (:mod:`mitsuba_p3.fit.noise`):
a Gaussian (sigma = the residuals' RMS) and an inlier/outlier mixture. Both describe
the residuals at the true geometry; the question for inference is which one ranks
*hypotheses* right. For evenly spaced images of the train split (the classes the
model was fitted on; the test split is never read), this samples the P3 posterior
with tempered SMC (:mod:`mitsuba_p3.infer.smc`) under each form and prints JSON:
the share of images whose most probable shape, and whose posterior-mean size
class, match the labels, the mean log p(true shape), and seconds per image.

    python scripts/select_noise.py --dataset data/fsclvr --model data/models/fsclvr [--images 30]
        [--forms fitted,robust] [--particles 32] [--islands 1]
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.smc import SMCConfig, sample_smc, shape_weights


def size_class(scale: np.ndarray, sizes: dict[str, float]) -> str:
    """The size name whose half-extent is nearest in log to the posterior mean's (geometric) half-extent."""
    value = float(np.exp(np.mean(np.log(scale))))
    return min(sizes, key=lambda name: abs(np.log(sizes[name]) - np.log(value)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--images", type=int, default=30, help="evenly spaced train images")
    parser.add_argument("--forms", default="fitted,robust")
    parser.add_argument("--particles", type=int, default=SMCConfig.particles)
    parser.add_argument("--islands", type=int, default=SMCConfig.islands, help="independent SMC runs, pooled")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    shots = dataset.split("train")
    shots = [shots[i] for i in np.linspace(0, len(shots) - 1, min(args.images, len(shots))).astype(int)]
    # the train labels' half-extents per size name (the size rule of the attributes, learnt on train)
    sizes = {}
    for shot in dataset.split("train"):
        sizes.setdefault(shot.cls.size, []).append(float(np.exp(np.mean(np.log(shot.scale)))))
    sizes = {name: float(np.median(v)) for name, v in sizes.items()}
    config = SMCConfig(particles=args.particles, islands=args.islands)
    report = {"dataset": args.dataset, "images": len(shots),
              "smc": {"particles": config.particles, "islands": config.islands}}
    for form in [f.strip() for f in args.forms.split(",") if f.strip()]:
        core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=form), "mitsuba",
                             *dataset.resolution)
        shape_right, size_right, log_true, seconds = [], [], [], []
        for i, shot in enumerate(shots):
            start = time.perf_counter()
            run = sample_smc(core, core.observe(dataset.image(shot)), config)
            seconds.append(time.perf_counter() - start)
            weights = shape_weights(run.statistics)
            shape_right.append(max(weights, key=weights.get) == shot.cls.shape)
            log_true.append(float(np.log(max(weights[shot.cls.shape], 1e-12))))
            scale = np.exp(run.positions[..., 3:6].reshape(-1, 3)).mean(axis=0)
            size_right.append(size_class(scale, sizes) == shot.cls.size)
            print(f"{form} {i + 1}/{len(shots)} {shot.class_name}: shape {'ok' if shape_right[-1] else 'WRONG'} "
                  f"size {'ok' if size_right[-1] else 'WRONG'} {seconds[-1]:.1f} s", flush=True)
        report[form] = {"shape": float(np.mean(shape_right)), "size": float(np.mean(size_right)),
                        "mean_log_p_true_shape": float(np.mean(log_true)),
                        "seconds_per_image": float(np.median(seconds))}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
