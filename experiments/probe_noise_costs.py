"""What a noise form charges for a misplaced object: the log-likelihood drop, against the true pose, of
the object shifted sideways by 1, 2, 5 and 10 mm and moved out of the scoring window altogether,
for evenly spaced train images (the classes the model was fitted on), on the window the SMC scores.

A likelihood that keeps the outline charges more the further the object moves, and most for an
object that is not there; one that charges a 2 mm shift more than an absent object sends the
sampler to the empty window (it has more prior volume than a needle-sharp peak). Prints one JSON
row per image and form, then the median drop per shift and form.

    python experiments/probe_noise_costs.py data/fsclvr --model data/models/fsclvr [--images 12]
        [--forms fitted,sandwich,spectral]
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.infer.likelihood import score
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood

SHIFTS_MM = (1.0, 2.0, 5.0, 10.0, 300.0)   # the last: out of the window


def main() -> None:
    import jax.numpy as jnp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--model", required=True)
    parser.add_argument("--images", type=int, default=12)
    parser.add_argument("--forms", default="fitted,sandwich,spectral")
    args = parser.parse_args()
    dataset, fitted = load_dataset(args.dataset), FittedModel(args.model)
    materials = fitted.materials
    shots = dataset.split("train")
    shots = [shots[i] for i in np.linspace(0, len(shots) - 1, min(args.images, len(shots))).astype(int)]
    drops = {}
    for form in [f.strip() for f in args.forms.split(",") if f.strip()]:
        core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=form), "mitsuba", *dataset.resolution)
        for shot in shots:
            image = dataset.image(shot)
            window = core.window_for(image, SCORING_WINDOW) or (0, 0, *dataset.resolution)
            top, left, height, width = window
            observation = core.observe(image, window if (height, width) != dataset.resolution else None)
            truth = shot_params(shot, materials)
            renders = []
            for shift in (0.0,) + SHIFTS_MM:
                moved = dict(truth, shift=truth["shift"] + np.array([shift / 1000, 0], np.float32))
                renders.append(core.renderer.render(moved)[top:top + height, left:left + width])
            values = np.asarray(score(observation, jnp.asarray(np.stack(renders)), core.config))
            row = {"form": form, "class": shot.class_name, "index": shot.index,
                   **{f"drop_{s:g}mm": float(values[0] - v) for s, v in zip(SHIFTS_MM, values[1:])}}
            print(json.dumps(row), flush=True)
            drops.setdefault(form, []).append([row[f"drop_{s:g}mm"] for s in SHIFTS_MM])
    summary = {form: {f"{s:g} mm": round(float(np.median(np.asarray(v)[:, i])), 1) for i, s in enumerate(SHIFTS_MM)}
               for form, v in drops.items()}
    for form, v in drops.items():
        v = np.asarray(v)
        summary[form]["images where absent is cheaper than 2 mm"] = int(np.sum(v[:, -1] < v[:, 1]))
        summary[form]["images where absent is cheaper than 10 mm"] = int(np.sum(v[:, -1] < v[:, -2]))
    print(json.dumps({"dataset": args.dataset, "images": len(shots), "median_drop_nats": summary}, indent=1))


if __name__ == "__main__":
    main()
