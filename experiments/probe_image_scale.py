"""How much worse than its train images does the model render an image? Each cached posterior's noise scale.

The scaled noise form (``--noise scaled``; :mod:`mitsuba_p3.fit.fields`, "An image's own scale") integrates an
image's noise scale s^2 out under a prior fitted on the train windows at the truth. How far it tempers an image's
evidence is set by that image's own estimate of s^2: the quadratic form q = r' C_1^-1 r of its best pose over
the window's effective count n (q / n, about 1 on a train window at the truth). This probe reads, for every
posterior cached by ``mitsuba-p3 evaluate``, the particle with the highest log likelihood across its runs,
renders it in the run's scoring window and prints q / n, the posterior mean of s^2 under the fitted prior,
(b + q / 2) / (a + n / 2 - 1), and the Phong misfit of the run's ``attributes.csv`` where it has one; then
the quantiles per split.

    python experiments/probe_image_scale.py data/fsclvr-lo data/models/fsclvr-scaled out/eval-fsclvr
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.likelihood import fields_parts
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood


def image_scale(core: PosteriorCore, observed: np.ndarray, cached) -> tuple[float, float]:
    """(q, n) of a cached posterior's best particle: its quadratic form in the run's window, and the window's
    effective count (the fitted fields' power x its values)."""
    import jax.numpy as jnp

    runs, particles, _ = cached["particles_position"].shape
    best = np.unravel_index(np.argmax(cached["particles_loglikelihood"]), (runs, particles))
    z = jnp.asarray(cached["particles_position"][best])
    window = tuple(int(v) for v in cached["particles_window"])
    observation = core.observe(observed, window=window if window[2] > 0 else None)
    image, objects = core._image(z, observation)
    _, form = fields_parts(observation["image"], image[None], objects[None], observation["empty"], core.config,
                           core.params(z)["colour"][None])
    return float(form[0]), float(core.config.scale[2] * np.prod(image.shape))


def misfits(run: Path) -> dict[int, float]:
    """The Phong misfit per image index of a run's ``attributes.csv`` (empty without one)."""
    path = run / "attributes.csv"
    if not path.exists():
        return {}
    with path.open() as f:
        rows = list(csv.DictReader(f))
    return {int(r["query"]): float(r["misfit"]) for r in rows if r["model"] == "p3" and r.get("misfit")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("dataset")
    parser.add_argument("model", help="a model whose noise stage fitted the scale's prior")
    parser.add_argument("run", type=Path, help="an evaluation folder with cached posteriors")
    parser.add_argument("--limit", type=int, default=None, help="at most this many images per split")
    args = parser.parse_args()
    dataset, fitted = load_dataset(args.dataset), FittedModel(args.model)
    config = default_likelihood(fitted, "p3", noise="scaled")
    shape, rate = config.scale[:2]
    paths = sorted((args.run / "posteriors" / "p3").glob("*.npz"))
    height, width = dataset.image(dataset.shots[int(paths[0].stem)]).shape[:2]
    core = PosteriorCore.shared(fitted, config, "mitsuba", height, width)
    misfit = misfits(args.run)
    by_split: dict[str, list[float]] = {}
    print(f"prior s^2 ~ IG({shape:.2f}, {rate:.2f})")
    print(f"{'image':>5s} {'split':5s} {'class':32s} {'q/n':>6s} {'E s^2':>6s} {'misfit':>6s}")
    for path in paths:
        index = int(path.stem)
        shot = dataset.shots[index]
        split = "train" if shot in dataset.split("train") else "test"
        if args.limit is not None and len(by_split.get(split, [])) >= args.limit:
            continue
        form, count = image_scale(core, dataset.image(shot), np.load(path))
        mean = (rate + form / 2) / (shape + count / 2 - 1)
        by_split.setdefault(split, []).append(form / count)
        m = misfit.get(index)
        print(f"{index:5d} {split:5s} {shot.class_name:32s} {form / count:6.2f} {mean:6.2f} "
              f"{'' if m is None else f'{m:6.2f}'}", flush=True)
    for split, ratios in by_split.items():
        q = np.quantile(ratios, [0.1, 0.5, 0.9, 0.99])
        print(f"{split}: {len(ratios)} images, q/n quantiles 10/50/90/99%: " + " / ".join(f"{v:.2f}" for v in q))


if __name__ == "__main__":
    main()
