"""Would anti-aliased renders match the path tracer's outlines better? The fitted world rendered with
f x f rays per pixel (a render at f times the resolution, averaged over each pixel's f x f block), at
the train split's true geometry with the fitted materials: the RMS on the outline's pixels (a pixel
either side of it) and over the whole image, f = 1, 2, 3. The path tracer averages many rays over each
pixel's square; the Phong renders shoot one ray through its centre.

    python experiments/probe_supersampling.py DATA_ROOT MODEL_FOLDER
"""
import argparse

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.render import make_renderer
from probe_residuals import outline


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("model")
    args = parser.parse_args()
    model, data = FittedModel(args.model), load_dataset(args.data)
    shots, materials = data.split("train"), model.materials
    height, width = data.resolution
    base = make_renderer(model.scene(), "mitsuba", height=height, width=width, shadows=True)
    empty = base.render_empty()
    for factor in (1, 2, 3):
        renderer = make_renderer(model.scene(), "mitsuba", height=height * factor, width=width * factor, shadows=True)
        edge_sq, total_sq = [], []
        for shot in shots:
            params = shot_params(shot, materials)
            image = renderer.render(params).reshape(height, factor, width, factor, 3).mean(axis=(1, 3))
            squared = (image - data.image(shot)) ** 2
            edge = outline(base.surface_ids(params) == 2)
            edge_sq.append(squared[edge].mean())
            total_sq.append(squared.mean())
        floor = renderer.render_empty().reshape(height, factor, width, factor, 3).mean(axis=(1, 3))
        print(f"{factor}x{factor} rays per pixel: outline RMS {np.sqrt(np.mean(edge_sq)):.4f}, whole image RMS "
              f"{np.sqrt(np.mean(total_sq)):.5f}, empty floor vs one ray {np.abs(floor - empty).mean():.4f}", flush=True)


if __name__ == "__main__":
    main()
