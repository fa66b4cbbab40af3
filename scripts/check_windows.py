"""Is the scoring window on the object? The SMC scores only a window around the image's footprint
(:meth:`mitsuba_p3.infer.model.PosteriorCore.window_for`); a window placed on a shadow, a border or
a texture instead of the object makes the posterior about nothing. This checks every image of a
split: it renders the labelled object with the fitted model at its true pose, and reports each
image whose window holds less than ``--cover`` of the object's pixels (an image scored whole, as
happens when the footprint is too large for the window, is counted apart: every pixel is scored). Prints JSON; exit status 1 if any image
misses, so it can gate a run.

    python scripts/check_windows.py data/fsclvr --model data/models/fsclvr [--split test] [--cover 0.9]
"""
from __future__ import annotations

import argparse
import json
import sys

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.fit.scene_opt import geometry_of
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood


def object_mask(renderer, empty, shot) -> np.ndarray:
    """(H, W) the labelled object's own pixels: where the fitted scene without shadows, the object
    lit by ambient light alone, differs from the empty floor."""
    params = {**geometry_of(shot), "colour": np.ones(3, np.float32), "ambient": np.float32(1.0),
              "diffuse": np.float32(0.0), "specular": np.float32(0.0), "shininess": np.float32(1.0)}
    return np.any(np.abs(renderer.render(params) - empty) > 1e-3, axis=-1)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--model", required=True)
    parser.add_argument("--split", default="test", choices=("train", "test"))
    parser.add_argument("--cover", type=float, default=0.9, help="least share of the object's pixels inside")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    core = PosteriorCore(FittedModel(args.model), default_likelihood(FittedModel(args.model), "p3", noise="fitted"),
                         "mitsuba", *dataset.resolution)
    from mitsuba_p3.render import make_renderer

    plain = make_renderer(core.fitted.scene(), "mitsuba", height=dataset.resolution[0], width=dataset.resolution[1],
                          shadows=False)
    empty = plain.render_empty()
    misses, covered, whole = [], [], 0
    for shot in dataset.split(args.split):
        image = dataset.image(shot)
        window = core.window_for(image, SCORING_WINDOW)
        mask = object_mask(plain, empty, shot)
        if window is None:                   # scored whole: every object pixel is scored
            share, whole = 1.0, whole + 1
        else:
            top, left, height, width = window
            share = float(mask[top:top + height, left:left + width].sum() / max(mask.sum(), 1))
        covered.append(share)
        if share < args.cover:
            misses.append({"index": shot.index, "class": shot.class_name, "file": str(shot.file),
                           "window": window, "object_share_inside": round(share, 3)})
    report = {"dataset": args.dataset, "split": args.split, "images": len(covered),
              "window": list(SCORING_WINDOW), "cover": args.cover, "misses": len(misses),
              "scored_whole": whole,
              "min_object_share_inside": round(min(covered), 3), "missed": misses}
    print(json.dumps(report, indent=1))
    return 1 if misses else 0


if __name__ == "__main__":
    sys.exit(main())
