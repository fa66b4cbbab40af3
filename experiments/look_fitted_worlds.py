"""Do the fitted worlds cast the images' shadows? Each image's truth rendered under each model's world (a figure).

For the named images of a split, one row each: the image, then per model its truth rendered in that model's
fitted world (true geometry, the fit's material of its class, hard shadows, as the likelihood renders) and the
residual (image minus render, 0.5 gray is none). A shadow that falls where the image has none, or a highlight on
the wrong side, shows at a glance where a number would hide it. The title of each render gives the model's train
mean squared error of the fit (all pixels) for reference.

    python experiments/look_fitted_worlds.py data/fsclvr-lo --models data/models/fsclvr-fields3,data/models/fsclvr-falloff \\
        --split train --images small-gray-metal-cube/0,large-brown-rubber-sphere/1 --out FIGURE.png
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.render import make_renderer
from probe_fields_power import materials_for


def main() -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--models", required=True, help="comma-separated fitted-model folders")
    parser.add_argument("--images", required=True, help="comma-separated CLASS/NUMBER of the split")
    parser.add_argument("--split", default="train", choices=("train", "test"))
    parser.add_argument("--out", required=True, help="the figure (.png)")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    wanted = args.images.split(",")
    by_name = {f"{s.class_name}/{s.file.stem}": s for s in dataset.split(args.split)}
    missing = [name for name in wanted if name not in by_name]
    if missing:
        parser.error(f"no image(s) {missing} in {args.dataset}'s {args.split} split")
    models = [FittedModel(path) for path in args.models.split(",")]
    renderers = [make_renderer(m.scene(), "mitsuba", *dataset.resolution, shadows=True) for m in models]
    fig, axes = plt.subplots(len(wanted), 1 + 2 * len(models), figsize=(2.6 * (1 + 2 * len(models)), 2.1 * len(wanted)),
                             squeeze=False)
    for row, name in enumerate(wanted):
        shot = by_name[name]
        image = dataset.image(shot)
        axes[row, 0].imshow(image)
        axes[row, 0].set_title(name, fontsize=7)
        for k, (model, renderer) in enumerate(zip(models, renderers)):
            params = {key: np.asarray(v, np.float32)
                      for key, v in shot_params(shot, materials_for(shot, model.materials)).items()}
            render = np.asarray(renderer.render(params))
            mse = model.info["stages"]["scene"]["final_mean_squared_error"]
            axes[row, 1 + 2 * k].imshow(np.clip(render, 0, 1))
            axes[row, 1 + 2 * k].set_title(f"{Path(model.root).name} (fit MSE {mse:.2e})", fontsize=7)
            axes[row, 2 + 2 * k].imshow(np.clip(0.5 + image - render, 0, 1))
            axes[row, 2 + 2 * k].set_title("image - render", fontsize=7)
    for ax in axes.ravel():
        ax.set_axis_off()
    fig.tight_layout()
    fig.savefig(args.out, dpi=110)
    print(f"wrote {args.out}")


if __name__ == "__main__":
    main()
