"""Does the model see the shape? Each shape hypothesis at the image's true pose, its material by least squares.

For evenly spaced images of a split, renders the object at its labelled position,
yaw and size as each shape class (hard shadows as the fitted noise model has them),
fits its material exactly by least squares on the material bases for each shininess
of ``--shininess`` (:func:`mitsuba_p3.fit.materials.fit_material`), and keeps the
lowest squared error per shape. Prints JSON: the share of images where the true
shape has the lowest error (overall and per true shape), and the median margin to
the runner-up in squared error and in nats under the model's fitted Gaussian noise
(margin * beta / (2 sigma^2)).

If the true shape wins here but not in the posterior, the sampler may be what misses
(it does not reach the true pose and material of the true shape); if it loses
here, the renderer and likelihood cannot tell the shapes apart. The wrong shapes are
scored at the *true* pose too, where they are not at their best, so the margin here
overstates what the image holds: with ``--smc``, compare each shape's best particle
(``smc_max_log_likelihood``) with the truth's likelihood on the same pixels.

    python experiments/shape_at_truth.py --dataset data/fsclvr --model data/models/fsclvr [--split train] [--every 3] [--size small]
        [--classes small-blue-metal-sphere,...] [--smc] [--noise fields|fitted|...]

With ``--smc`` it also runs the default SMC on each image and prints, per shape, the
log likelihood at the truth under ``--noise`` (the default's noise unless given; the
better of the least-squares material and the class's fitted material) beside the SMC's
log evidence and best particle: a true shape that wins at the truth but whose evidence
falls far below its likelihood there is a run that missed the pose; a wrong shape whose
best particle beats the truth is the likelihood's own preference. The summary then adds, for each of the
three figures, the true shape's margin over the best wrong shape (median, least, images it leads in).
"""
from __future__ import annotations

import argparse
import json

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.materials import fit_material
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.fit.scene_opt import geometry_of
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE, NOISES
from mitsuba_p3.render import make_renderer
from mitsuba_p3.shapes import SHAPES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--split", default="train", choices=("train", "test"))
    parser.add_argument("--every", type=int, default=3, help="every n-th image of the split")
    parser.add_argument("--size", choices=("small", "large"), help="only objects of this size")
    parser.add_argument("--shininess", default="4,64", help="shininess values tried per shape")
    parser.add_argument("--classes", help="only these classes (comma-separated names)")
    parser.add_argument("--smc", action="store_true", help="compare with the default SMC's evidence, per image")
    parser.add_argument("--noise", default=DEFAULT_NOISE, choices=NOISES, help="the likelihood's noise form (--smc)")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    noise = fitted.noise
    renderer = make_renderer(fitted.scene(), "mitsuba", *dataset.resolution, shadows=noise.shadows)
    start_material = {"colour": np.full(3, 0.5, np.float32), "ambient": np.float32(0.3),
                      "diffuse": np.float32(0.5), "specular": np.float32(0.2)}
    wins, margins, per_shape = [], [], {shape: [] for shape in SHAPES}
    smc_margins = {"log_likelihood_at_truth": [], "smc_max_log_likelihood": [], "smc_log_evidence": []}
    shots = [s for s in dataset.split(args.split) if args.size in (None, s.cls.size)
             and (args.classes is None or s.class_name in args.classes.split(","))]
    for shot in shots[::args.every]:
        observed = dataset.image(shot)
        errors, materials = [], []
        for k in range(len(SHAPES)):
            best = (np.inf, None)
            for alpha in (float(a) for a in args.shininess.split(",")):
                params = {**geometry_of(shot), "kappa": np.int32(k), **start_material, "shininess": np.float32(alpha)}
                material, error = fit_material(observed[None], renderer.render_bases(params)[None], np.full(3, 0.5))
                best = min(best, (error, {**params, **material}), key=lambda b: b[0])
            errors.append(best[0])
            materials.append(best[1])
        errors = np.array(errors)
        if args.smc:
            row = compare_smc(fitted, dataset, shot, observed, materials, args.noise)
            print(json.dumps(row), flush=True)
            for key, values in smc_margins.items():
                values.append(true_shape_margin(row, shot.cls.shape, key))
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
                      "median_margin_nats": margin * noise.power / (2 * sigma ** 2),
                      **({"smc_true_shape_margin_nats": {key: margin_summary(values) for key, values in smc_margins.items()}}
                         if args.smc else {})}, indent=2))


def true_shape_margin(row: dict, true_shape: str, key: str) -> float:
    """The true shape's ``key`` (a :func:`compare_smc` figure) less the best wrong shape's, in nats."""
    return row[true_shape][key] - max(row[shape][key] for shape in SHAPES if shape != true_shape)


def margin_summary(values: list[float]) -> dict:
    """Median and least margin, and how many images the true shape leads in."""
    values = np.asarray(values)
    return {"median": round(float(np.median(values)), 1), "min": round(float(values.min()), 1),
            "true_shape_ahead": [int((values > 0).sum()), len(values)]}


def compare_smc(fitted: FittedModel, dataset, shot, observed: np.ndarray, truths: list[dict],
                noise: str = DEFAULT_NOISE) -> dict:
    """Per shape: the log likelihood at the truth (``truths``: contract parameters, one per shape; the
    better of that material and the class's fitted one) and the default SMC's log evidence and best
    particle, under the noise form ``noise``."""
    import jax.numpy as jnp

    from mitsuba_p3.infer.model import PosteriorCore
    from mitsuba_p3.infer.posterior import default_likelihood
    from mitsuba_p3.infer.smc import sample_smc

    core = PosteriorCore.shared(fitted, default_likelihood(fitted, "p3", noise=noise), "mitsuba",
                                *dataset.resolution)
    run = sample_smc(core, core.observe(observed))
    # the truth is scored on the pixels the SMC scored (its window around the footprint, if any)
    window = run.statistics["window"]
    observation = core.observe(observed, tuple(window) if window else None)
    row = {"image": shot.file.name, "class": shot.class_name}
    fitted_material = fitted.materials.get(f"{shot.cls.colour}-{shot.cls.material}")

    def at_truth(k: int, truth: dict, material: dict) -> float:
        x = {"shift": truth["shift"][None], "theta": np.array([truth["theta"]]), "scale": truth["scale"][None],
             "class_probabilities": (np.eye(3)[k] * 0.998 + 0.001)[None],
             "colour": np.clip(np.asarray(material["colour"], np.float64), 1e-3, 1 - 1e-3)[None],
             **{name: np.array([material[name]]) for name in ("ambient", "diffuse", "specular", "shininess")}}
        z = jnp.asarray(core.prior.unconstrain(x)[0], jnp.float32)
        return float(core.log_likelihood(z, observation))

    for k, (shape, truth) in enumerate(zip(SHAPES, truths)):
        scores = [at_truth(k, truth, truth)] + ([at_truth(k, truth, fitted_material)] if fitted_material else [])
        row[shape] = {"log_likelihood_at_truth": round(max(scores), 1),
                      "smc_log_evidence": round(run.statistics["hypotheses"][shape]["log_evidence"], 1),
                      "smc_max_log_likelihood": round(run.statistics["hypotheses"][shape]["max_log_likelihood"], 1)}
    return row


if __name__ == "__main__":
    main()
