"""Does the model see the shape? Each shape hypothesis at the image's true pose, its material by least squares.

For evenly spaced images of a split, renders the object at its labelled position,
yaw and size as each shape class (hard shadows as the fitted noise model has them),
fits its material exactly by least squares on the material bases for each shininess
of ``--shininess`` (:func:`mitsuba_p3.fit.materials.fit_material`), and keeps the
lowest squared error per shape. Prints JSON: the share of images where the true
shape has the lowest error (overall and per true shape), and the median margin to
the runner-up in squared error and in nats under the model's fitted Gaussian noise
(margin * beta / (2 sigma^2)).

If the true shape wins here but not in the posterior, the sampler is what misses
(it does not reach the true pose and material of the true shape); if it loses
here, the renderer and likelihood cannot tell the shapes apart.

    python scripts/shape_at_truth.py --dataset data/fsclvr --model data/models/fsclvr [--split train] [--every 3]
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.materials import fit_material
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.fit.scene_opt import geometry_of
from mitsuba_p3.render import make_renderer
from mitsuba_p3.shapes import SHAPES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--split", default="train", choices=("train", "test"))
    parser.add_argument("--every", type=int, default=3, help="every n-th image of the split")
    parser.add_argument("--shininess", default="4,64", help="shininess values tried per shape")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    noise = fitted.noise
    renderer = make_renderer(fitted.scene(), "mitsuba", *dataset.resolution, shadows=noise.shadows)
    start_material = {"colour": np.full(3, 0.5, np.float32), "ambient": np.float32(0.3),
                      "diffuse": np.float32(0.5), "specular": np.float32(0.2)}
    wins, margins, per_shape = [], [], {shape: [] for shape in SHAPES}
    for shot in dataset.split(args.split)[::args.every]:
        observed = dataset.image(shot)
        errors = []
        for k in range(len(SHAPES)):
            best = np.inf
            for alpha in (float(a) for a in args.shininess.split(",")):
                params = {**geometry_of(shot), "kappa": np.int32(k), **start_material, "shininess": np.float32(alpha)}
                _, error = fit_material(observed[None], renderer.render_bases(params)[None], np.full(3, 0.5))
                best = min(best, error)
            errors.append(best)
        errors = np.array(errors)
        right = bool(errors.argmin() == SHAPES.index(shot.cls.shape))
        wins.append(right)
        per_shape[shot.cls.shape].append(right)
        margins.append(float(np.sort(errors)[1] - errors.min()))
    sigma = noise.gaussian_sigma if noise.gaussian_sigma is not None else noise.sigma
    margin = float(np.median(margins))
    print(json.dumps({"dataset": args.dataset, "split": args.split, "images": len(wins),
                      "true_shape_lowest_error": float(np.mean(wins)),
                      "per_true_shape": {s: [int(sum(v)), len(v)] for s, v in per_shape.items()},
                      "median_margin_squared_error": margin,
                      "median_margin_nats": margin * noise.power / (2 * sigma ** 2)}, indent=2))


if __name__ == "__main__":
    main()
