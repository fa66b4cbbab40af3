"""Where should the fields' power act? One image's truth and a run's best draws under both readings.

The shading fields' density is a Gaussian N(r; 0, sigma^2 I + B T B') (:mod:`mitsuba_p3.fit.fields`), and the
composite likelihood's power beta (1 / the correlation area the fields leave) can temper either the whole
marginal, ``beta * log N(r; 0, sigma^2 I + B T B')`` (the form before 2026-11-27's second change: the fields'
prior tempered too, as if their scales were tau / sqrt(beta)), or the pixels given the fields,
``log N(r; 0, (sigma^2 / beta) I + B T B')`` up to a constant (the fields keep their fitted prior; the form
now). For one image this scores, under both and under the fitted Gaussian: the truth (its labelled pose and
the fit's material of its class, or of its kind where the fit never saw its colour), the truth painted black (colour 0.02: a field would have to supply all of
its shade), and the best draw of each shape class in a posterior saved by ``mitsuba-p3 infer``. A draw of
the wrong shape that outscores the truth's best draws only under one reading is that reading's doing.

    python experiments/probe_fields_power.py data/fsclvr-lo --model data/models/fsclvr-fields3 \\
        --image large-gray-rubber-sphere/5 --posterior RUN/posterior.nc [--split test]
"""
from __future__ import annotations

import argparse
import json
from dataclasses import replace

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.shapes import SHAPES


def add_case_arguments(parser: argparse.ArgumentParser) -> None:
    """The arguments naming one image and a posterior of it (shared with ``probe_light_turn.py``)."""
    parser.add_argument("dataset")
    parser.add_argument("--model", required=True)
    parser.add_argument("--image", required=True, help="CLASS/NUMBER of the split, e.g. large-gray-rubber-sphere/5")
    parser.add_argument("--posterior", required=True, help="posterior.nc of mitsuba-p3 infer on that image")
    parser.add_argument("--split", default="test", choices=("train", "test"))


def load_case(args, parser: argparse.ArgumentParser):
    """(data set, fitted model, image, truth, the posterior's positions (n, 15) and shape classes (n,)) of
    :func:`add_case_arguments`' arguments. The truth takes the fit's material of its class, or of its kind where
    the fit never saw its colour."""
    import arviz as az

    dataset, fitted = load_dataset(args.dataset), FittedModel(args.model)
    shots = [s for s in dataset.split(args.split) if f"{s.class_name}/{s.file.stem}" == args.image]
    if not shots:
        parser.error(f"no image {args.image} in {args.dataset}'s {args.split} split")
    shot = shots[0]
    materials = materials_for(shot, fitted.materials)
    posterior = az.from_netcdf(args.posterior).posterior
    draws = posterior["z"].values.reshape(-1, posterior["z"].shape[-1])
    return (dataset, fitted, dataset.image(shot), shot_params(shot, materials), draws,
            posterior["kappa"].values.reshape(-1))


def materials_for(shot, materials: dict) -> dict:
    """The fit's materials with one for ``shot``'s class: its own, or, for a colour the fit never saw (a test
    class), the fit's first material of its kind (shared with ``look_fitted_worlds.py``)."""
    materials = dict(materials)
    key = f"{shot.cls.colour}-{shot.cls.material}"
    if key not in materials:
        materials[key] = next(v for k, v in materials.items() if k.endswith("-" + shot.cls.material))
    return materials


def position_of(prior, params: dict) -> np.ndarray:
    """The unconstrained position of natural parameters whose shape class is ``params["kappa"]``."""
    probabilities = np.full(len(SHAPES), 0.01)
    probabilities[int(params["kappa"])] = 1.0 - 0.01 * (len(SHAPES) - 1)
    return prior.unconstrain({**{k: np.asarray(v) for k, v in params.items()}, "class_probabilities": probabilities})


def main() -> None:
    import jax
    import jax.numpy as jnp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_case_arguments(parser)
    args = parser.parse_args()
    dataset, fitted, image, truth, draws, kappa = load_case(args, parser)
    pixels = default_likelihood(fitted, "p3", noise="fields")
    beta = fitted.noise.fields["power"]
    forms = {"fields, pixels tempered (now)": pixels,
             "fields, whole marginal tempered (before)": replace(pixels, sigma=pixels.sigma * np.sqrt(beta), power=beta),
             "fitted": default_likelihood(fitted, "p3", noise="fitted")}

    fixed = {"truth": position_of(fitted.prior, truth),
             "truth painted black": position_of(fitted.prior, {**truth, "colour": np.full(3, 0.02)})}
    report = {"image": args.image, "fields_power": beta}
    for name, config in forms.items():
        core = PosteriorCore(fitted, config, "mitsuba", *dataset.resolution)
        observation = core.observe(image, core.window_for(image, SCORING_WINDOW))
        score = jax.jit(jax.vmap(lambda z: core.log_likelihood(z, observation)))
        of_draws = np.asarray(score(jnp.asarray(draws, jnp.float32)))
        of_fixed = np.asarray(score(jnp.asarray(np.stack(list(fixed.values())), jnp.float32)))
        row = {k: round(float(v), 1) for k, v in zip(fixed, of_fixed)}
        row.update({f"best {shape} draw": round(float(of_draws[kappa == k].max()), 1)
                    for k, shape in enumerate(SHAPES) if np.any(kappa == k)})
        report[name] = row
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
