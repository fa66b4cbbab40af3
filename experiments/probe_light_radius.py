"""How much soft shadows help the fitted model: train-split RMS of the fitted scene's renders
(true geometry, fitted materials) with every light widened to a disc of radius r, against the
images; r = 0 is the fit's hard shadows. Prints one line per radius with the render time.

    python experiments/probe_light_radius.py DATA_ROOT MODEL_FOLDER [--radii 0,0.01,...] [--samples 16]
"""
import argparse
import time

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.render import make_renderer


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("model")
    parser.add_argument("--radii", default="0,0.01,0.02,0.03,0.045,0.06,0.08")
    parser.add_argument("--samples", type=int, default=16)
    args = parser.parse_args()
    model, data = FittedModel(args.model), load_dataset(args.data)
    shots, materials = data.split("train"), model.materials
    observations = np.stack([data.image(s) for s in shots])
    height, width = data.resolution
    for radius in (float(r) for r in args.radii.split(",")):
        start = time.time()
        renderer = make_renderer(model.scene().replace(light_radius=radius), "mitsuba", height=height,
                                 width=width, shadows=True, shadow_samples=args.samples if radius > 0 else 1)
        renders = np.stack([renderer.render(shot_params(s, materials)) for s in shots])
        rms = float(np.sqrt(np.mean((renders - observations) ** 2)))
        print(f"{data.variant} radius {radius:.3f} m: train RMS {rms:.5f} ({time.time() - start:.1f} s, "
              f"{len(shots)} images)", flush=True)


if __name__ == "__main__":
    main()
