"""The neural likelihood's scale, measured on real (image, fitted render) pairs: prints JSON.

For each of the first ``--pairs`` train images of DATASET and its render by the fitted
MODEL (true geometry, fitted material), the NP3 neural term -0.05 * sum_m mean (F_m(I) - F_m(R))^2
over the model's selected channels, computed three ways:

- ``torchvision``: the network's own preprocessing (RGB in [0, 1], ImageNet mean and std), unscaled:
  what the project used before the paper scale;
- ``paper_scale``: the same features times PAPER_FEATURE_SCALE (255 x mean std), the project's default;
- ``keras_inputs``: the authors' preprocessing fed to these weights (0-255, mean subtracted, no std
  division), for the magnitude the paper's weight 0.05 was set for.

Beside them, the colour log-likelihood gap between the pair and an empty-floor render (the evidence
the object's pixels carry) under the fitted noise model and under the paper's sigma = 1.

    python experiments/neural_scale.py DATASET MODEL [--pairs 8]
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.features import IMAGENET_MEAN, IMAGENET_STD, PAPER_FEATURE_SCALE, selected_features
from mitsuba_p3.fit.model import FittedModel, render_train_split
from mitsuba_p3.infer.likelihood import LikelihoodConfig, colour_log_likelihood
from mitsuba_p3.infer.posterior import default_likelihood

WEIGHT = 0.05


def neural_term(real: np.ndarray, render: np.ndarray, channels, scale: float = 1.0, keras: bool = False) -> float:
    """-weight * sum over channels of the pixel mean of the squared feature difference."""
    # vgg_features normalises (x - mean) / std; feeding x' = mean + std * (255 x - 255 mean) makes the
    # network see 255 (x - mean): the authors' input scale (RGB order kept, as these weights expect)
    prepare = (lambda x: IMAGENET_MEAN + IMAGENET_STD * 255.0 * (x - IMAGENET_MEAN)) if keras else (lambda x: x)
    a = selected_features(prepare(real)[None], channels)
    b = selected_features(prepare(render)[None], channels)
    return -WEIGHT * scale ** 2 * float(sum(np.mean((np.asarray(x) - np.asarray(y)) ** 2) for x, y in zip(a, b)))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("model")
    parser.add_argument("--pairs", type=int, default=8)
    args = parser.parse_args()
    model = FittedModel(args.model)
    dataset = load_dataset(args.dataset)
    observations, renders = render_train_split(model, dataset, shadows=True)
    observations, renders = observations[:args.pairs], renders[:args.pairs]
    from mitsuba_p3.render import make_renderer

    empty = make_renderer(model.scene(), height=dataset.resolution[0], width=dataset.resolution[1],
                          shadows=True).render_empty()
    channels = model.channels
    rows = {"torchvision": [], "paper_scale": [], "keras_inputs": []}
    colour = {"fitted": [], "paper_sigma_1": []}
    likelihoods = {"fitted": default_likelihood(model, "p3", noise="fitted"),
                   "paper_sigma_1": LikelihoodConfig("p3", sigma=1.0)}
    for real, render in zip(observations, renders):
        rows["torchvision"].append(neural_term(real, render, channels))
        rows["paper_scale"].append(neural_term(real, render, channels, PAPER_FEATURE_SCALE))
        rows["keras_inputs"].append(neural_term(real, render, channels, keras=True))
        for name, config in likelihoods.items():
            pair = np.asarray(colour_log_likelihood(real, np.stack([render, empty]), config))
            colour[name].append(float(pair[0] - pair[1]))
    median = lambda v: float(np.median(v))  # noqa: E731
    print(json.dumps({
        "pairs": len(observations), "channels": [f"{c.layer}[{c.channel}]" for c in channels],
        "paper_feature_scale": PAPER_FEATURE_SCALE,
        "neural_term_nats_median": {k: median(v) for k, v in rows.items()},
        "keras_over_paper_scale_median": median(np.array(rows["keras_inputs"]) / np.array(rows["paper_scale"])),
        "colour_gap_object_vs_empty_floor_nats_median": {k: median(v) for k, v in colour.items()},
        "noise_model": {k: getattr(likelihoods["fitted"], k) for k in ("sigma", "outlier", "power")},
    }, indent=2))


if __name__ == "__main__":
    main()
