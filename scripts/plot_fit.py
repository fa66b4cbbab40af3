"""The training stage's figures from a fitted-model folder (nothing is refitted).

Writes into MODEL_DIR/figures/ (or --out):
  progress.png            observation beside the render after several epochs
  loss.png                the loss of every optimisation pass
  materials.png           every optimised material on a sphere, in the fitted world
  gmm_priors.png          the GMM priors over the optimised materials
  reparametrisation.png   prior samples before and after the bijectors, with p(z)
  prior_predictive.png    scenes drawn from the prior and rendered (Bayesian-workflow check)

Usage: python scripts/plot_fit.py MODEL_DIR [--out DIR] [--samples 24] [--seed 0]
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from mitsuba_p3 import plots
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.space import render_params
from mitsuba_p3.render import make_renderer
from mitsuba_p3.scene import Camera


def material_grid(model: FittedModel, path: Path) -> Path:
    """Each fitted material on a large sphere, seen close up in the fitted world."""
    scene = model.scene().replace(camera=Camera(origin=np.array([0.0, -0.2, 0.12]),
                                                target=np.array([0.0, 0.0, 0.035]), fov=30.0))
    renderer = make_renderer(scene, "mitsuba", height=96, width=128, shadows=True)
    images, titles = [], []
    for name, m in sorted(model.materials.items()):
        params = {"shift": np.zeros(2, np.float32), "theta": np.float32(0), "scale": np.full(3, 0.035, np.float32),
                  "kappa": np.int32(0), **{k: np.asarray(v, np.float32) for k, v in m.items()}}
        images.append(renderer.render(params))
        titles.append(f"{name}\nka {m['ambient']:.2f} kd {m['diffuse']:.2f} ks {m['specular']:.2f} "
                      f"a {m['shininess']:.1f}")
    return plots.image_grid(images, titles, path, columns=min(8, len(images)),
                            title=f"optimised materials ({model.info['dataset']['variant']})")


def prior_predictive(model: FittedModel, path: Path, samples: int, seed: int) -> Path:
    prior = model.prior
    x = prior.sample_constrained(np.random.default_rng(seed), samples)
    params = render_params(x)
    renderer = make_renderer(model.scene(), "mitsuba", height=120, width=160, shadows=False)
    images = renderer.render(params)
    names = ("sphere", "cube", "cylinder")
    titles = [f"{names[k]} s={np.mean(s) * 100:.1f} cm" for k, s in zip(params["kappa"], params["scale"])]
    return plots.image_grid(list(images), titles, path, columns=6, title="prior predictive samples")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model", type=Path)
    parser.add_argument("--out", type=Path, default=None)
    parser.add_argument("--samples", type=int, default=24)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model = FittedModel(args.model)
    out = args.out or args.model / "figures"
    variant = model.info["dataset"]["variant"]
    with np.load(args.model / "snapshots.npz") as data:
        snapshots = {k: data[k] for k in data.files}
    with open(args.model / "loss_curve.csv") as handle:
        rows = list(csv.DictReader(handle))
    written = [
        plots.optimisation_progress(snapshots, out / "progress.png", f"scene optimisation: {variant}"),
        plots.loss_curve(rows, out / "loss.png", f"scene optimisation loss: {variant}"),
        material_grid(model, out / "materials.png"),
        plots.gmm_priors(model.prior, model.materials, out / "gmm_priors.png"),
        plots.reparametrisation(model.prior, out / "reparametrisation.png", seed=args.seed),
        prior_predictive(model, out / "prior_predictive.png", args.samples, args.seed),
    ]
    for path in written:
        print(path)


if __name__ == "__main__":
    main()
