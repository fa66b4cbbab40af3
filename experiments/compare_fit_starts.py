"""Which start of the scene fit? One world fitted from several random starts of its lights, side by side.

The scene fit (:mod:`mitsuba_p3.fit.scene_opt`) starts its five point lights at random in a box
(``fit --seed``); Adam then finds a local optimum, and different starts find different ones (one
may turn a light nearly off). This fits a benchmark's train split once per seed (into
``OUT-sSEED``, or ``OUT`` itself for the default seed 777; folders that already hold a finished
fit are read, not refitted) and prints, per start, the figures a rule for keeping one start could
use, all on the train split:

- ``train_mse``: the fit's own objective at its end;
- ``fields_log_likelihood_per_pixel``: the train residuals' log likelihood under the noise model
  the posterior uses (the shading fields, :mod:`mitsuba_p3.fit.fields`);
- ``object_outlier``: the robust noise form's outlier weight on object pixels (how much of the
  object the fit leaves unexplained);
- the lights' intensities (a light near 0 is a light the fit turned off).

It prints JSON; which rule predicts the posteriors is judged with ``shape_at_truth.py --smc`` or train
posteriors (``sample_train_shots.py``), never on the test split.

    python experiments/compare_fit_starts.py data/studio-lo --out data/models/studio-white --seeds 777,1,2,3
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.fit.model import FittedModel, fit_model, start_figures as train_figures
from mitsuba_p3.fit.scene_opt import SceneOptConfig


def start_folder(out: Path, seed: int) -> Path:
    """The model folder of one start: ``out`` for the default seed, ``out-sSEED`` otherwise."""
    return out if seed == SceneOptConfig.seed else out.with_name(f"{out.name}-s{seed}")


def start_figures(folder: Path) -> dict:
    """The train figures of one fitted start (module docstring)."""
    model = FittedModel(folder)
    return {"model": str(folder), **train_figures(model),
            "light_colour": model.info["stages"]["scene"]["config"]["light_colour"],
            "object_outlier": model.noise.object_outlier,
            "light_intensity": [round(float(np.mean(light.intensity)), 3) for light in model.scene().lights]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", help="benchmark folder (its train split is fitted)")
    parser.add_argument("--out", required=True, type=Path, help="model folder of the default start (777)")
    parser.add_argument("--seeds", default="777,1,2,3", help="comma-separated seeds of the lights' start")
    parser.add_argument("--light-colour", default=SceneOptConfig.light_colour, help="as fit --light-colour")
    args = parser.parse_args()

    rows = []
    for seed in (int(s) for s in args.seeds.split(",")):
        folder = start_folder(args.out, seed)
        if not (folder / "noise.json").is_file():   # the last stage: a finished fit
            fit_model(args.dataset, folder, scene_config=SceneOptConfig(light_colour=args.light_colour, seed=seed))
        rows.append(start_figures(folder))
        print(json.dumps(rows[-1]), flush=True)
    best = {"train_mse": min(rows, key=lambda r: r["train_mse"])["seed"],
            "fields_log_likelihood_per_pixel": max(rows, key=lambda r: r["fields_log_likelihood_per_pixel"])["seed"]}
    print(json.dumps({"dataset": args.dataset, "starts": len(rows), "best_seed_by": best}, indent=2))


if __name__ == "__main__":
    main()
