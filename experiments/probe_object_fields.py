"""Would shading errors marginalised on the object's own pixels keep the outline? A probe on train images.

The fitted Gaussian's power beta = 1 / A divides all the evidence by the residuals' correlation area A,
and most of that correlation is the object's own: a metal's mirrored floor and sky, a rubber's soft
shading, the shadow's soft edge (``experiments/probe_residuals.py``). The stationary field
(``--noise spectral``) discounts such blobs anywhere, so an absent object borrows them. This probe
tries the other reading, the one the notebook names as the next step: the shading error is a smooth
field *on the pixels the hypothesis renders as object* (and another on its shadow), marginalised
analytically. Per channel the residual window r (P pixels) is

    r = B w + e,   w ~ N(0, diag(tau^2)),   e ~ N(0, sigma^2 I),

with B the object's (and shadow's) pixels times low-order polynomials of the pixel coordinates
(constant, linear, quadratic) and zero elsewhere, so that by Woodbury

    log p(r) = -1/2 (r'r - b'(sigma^2 / tau^2 + G)^-1 b) / sigma^2 - 1/2 log det(I + tau^2 G / sigma^2)
               - P/2 log(2 pi sigma^2),   G = B'B, b = B'r.

A field can change the object's shading but cannot move its outline (it lives on the rendered
mask), and an absent object has no mask to carry one. sigma and the taus are fitted by maximum
marginal likelihood on the first half of the train images at their true geometry; the power is
1 / (correlation area of the residuals left after the fields' posterior mean), the composite
likelihood's adjustment for what correlation remains. Then, on the other half, the log-likelihood
drop against the truth of: the object shifted 1, 2, 5, 10 mm, absent (300 mm away), each other
shape at the true pose and material, the true colour washed halfway out towards the gray of its own
brightness (what an achromatic field on a flat face forgives), and each other colour's fitted material of
the same kind at the true pose and shape (the nearest wrong colour: how much colour evidence the form keeps). Both forms
are printed side by side; larger drops for a wrong shape or an absent object, at the same drops for
small shifts, is what a likelihood that keeps the
outline should show.

    python experiments/probe_object_fields.py data/studio-lo --model data/models/studio-lo [--images 24]
        [--degree 1] [--regions split|joint] [--channels independent|achromatic|mixed|tinted] [--tint colour|render]
"""
from __future__ import annotations

import argparse
import json

import numpy as np
from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.fit.fields import CHANNELS, COLOURED, colour_tint, field_log_likelihood, fit_fields, monomials
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood

SHIFTS_MM = (1.0, 2.0, 5.0, 10.0, 300.0)


def gaussian_log_likelihood(r: np.ndarray, sigma: float) -> float:
    """The fitted form's density at power 1 (its truncation constant left out: it cancels in a drop)."""
    return float(-0.5 * np.sum(r * r) / sigma ** 2 - 0.5 * r.size * np.log(2 * np.pi * sigma ** 2))


def object_tint(render: np.ndarray, objects: np.ndarray) -> np.ndarray:
    """(3,) the colour a render (h, w, 3) gives the pixels its object covers (``objects`` (h, w)), scaled so
    that its channels' mean is 1 (:func:`~mitsuba_p3.fit.fields.colour_tint`'s scale; (1, 1, 1) when the
    object is absent or black): the tint with the light's colour and the highlight in it (``--tint render``)."""
    total = np.sum(np.asarray(render, np.float64) * np.asarray(objects, np.float64)[..., None], axis=(0, 1))
    mean = total.mean()
    return total / mean if mean > 1e-6 else np.ones(3)


def masks_of(core, params: dict, render: np.ndarray, empty: np.ndarray, crop) -> np.ndarray:
    """(2, h, w) the (object, shadow) masks of a window, as the likelihood makes them (:func:`fields_masks`):
    the object's silhouette, and the floor the render changes elsewhere."""
    import jax.numpy as jnp

    from mitsuba_p3.infer.likelihood import fields_masks
    from mitsuba_p3.render.jax_tracer import silhouette

    origin, rays = core.camera_rays
    obj = np.asarray(silhouette({k: jnp.asarray(v) for k, v in params.items()}, origin, rays,
                                core.renderer.floor_half_size)).reshape(core.renderer.height, core.renderer.width)[crop]
    return np.asarray(fields_masks(jnp.asarray(render), obj, empty), float)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--model", required=True)
    parser.add_argument("--images", type=int, default=24, help="train images: half fit, half probe")
    parser.add_argument("--degree", type=int, default=1)
    parser.add_argument("--regions", choices=("split", "joint"), default="split",
                        help="fields on the object and on its shadow apart (split) or on both as one region")
    parser.add_argument("--channels", choices=CHANNELS, default="independent",
                        help="fields per colour channel, shared by the three (achromatic), a shared constant "
                             "(mixed), or the object's in its own colour (tinted)")
    parser.add_argument("--tint", choices=("colour", "render"), default="colour",
                        help="tinted fields: the object's colour parameter, or the colour its render shows")
    args = parser.parse_args()
    dataset, fitted = load_dataset(args.dataset), FittedModel(args.model)
    core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise="fitted"), "mitsuba", *dataset.resolution)
    shots = dataset.split("train")
    shots = [shots[i] for i in np.linspace(0, len(shots) - 1, min(args.images, len(shots))).astype(int)]
    renderer, empty_full = core.renderer, np.asarray(core.empty)
    basis = monomials(*SCORING_WINDOW, args.degree)

    def window_parts(shot, params):
        image = dataset.image(shot)
        window = core.window_for(image, SCORING_WINDOW)
        if window is None:            # no footprint found: nothing to probe in this image
            return None
        top, left, h, w = window
        crop = (slice(top, top + h), slice(left, left + w))
        render = renderer.render(params)[crop]
        masks = masks_of(core, params, render, empty_full[crop], crop)
        return image[crop], render, masks if args.regions == "split" else np.stack([masks.sum(0), 0 * masks[0]])

    def tint_of(render, masks, params):
        if args.tint == "render":
            return object_tint(render, masks[0])
        colour = np.clip(np.asarray(params["colour"], np.float64), 0.0, 1.0)
        return colour_tint(colour)

    cases, missed = [], []
    for n, shot in enumerate(shots):
        truth = shot_params(shot, fitted.materials)
        parts = window_parts(shot, truth)
        if parts is None:
            missed.append(f"{shot.class_name}/{shot.index}")
            continue
        image, render, masks = parts
        cases.append((shot, truth, image - render, tint_of(render, masks, truth), masks))
    if missed:
        print(json.dumps({"no footprint window (skipped)": missed}), flush=True)
    fit_half, probe_half = cases[0::2], cases[1::2]

    # maximum marginal likelihood of sigma and the taus on the first half
    noise, figures = fit_fields(np.stack([r for *_, r, _, _ in fit_half]), np.stack([m for *_, m in fit_half]),
                                args.degree, args.channels, tints=np.stack([t for *_, t, _ in fit_half]))
    variances, fitted_power = noise.variances(), float(core.config.power)
    print(json.dumps({"fitted_power": fitted_power, **figures}), flush=True)

    def fields(r, masks, tint):
        loading = noise.loadings(tint) if noise.channels in COLOURED else noise.loadings()
        return noise.power * float(field_log_likelihood(r, masks, noise.sigma, variances, basis, loading=loading))

    names = [f"{s:g}mm" for s in SHIFTS_MM] + [f"shape{k}" for k in range(3)] + ["washed out"]
    drops, true_shapes = {"fitted": [], "fields": []}, []
    for shot, truth, r0, t0, B0 in probe_half:
        variants = [dict(truth, shift=truth["shift"] + np.array([s / 1000, 0], np.float32)) for s in SHIFTS_MM]
        variants += [dict(truth, kappa=np.int32(k)) for k in range(3)]
        kind = shot.cls.material
        others = [key for key in fitted.materials if key.endswith("-" + kind) and key != f"{shot.cls.colour}-{kind}"]
        # the true colour washed halfway out towards the gray of its own brightness
        grey = np.full(3, float(np.mean(truth["colour"])), np.float32)
        variants.append(dict(truth, colour=np.asarray(0.5 * truth["colour"] + 0.5 * grey, np.float32)))
        variants += [dict(truth, **{k: np.asarray(v, np.float32) for k, v in fitted.materials[key].items()})
                     for key in others]
        base = {"fitted": fitted_power * gaussian_log_likelihood(r0, core.config.sigma),
                "fields": fields(r0, B0, t0)}
        row = {"fitted": [], "fields": []}
        for params in variants:
            image, render, masks = window_parts(shot, params)
            r = image - render
            row["fitted"].append(base["fitted"] - fitted_power * gaussian_log_likelihood(r, core.config.sigma))
            row["fields"].append(base["fields"] - fields(r, masks, tint_of(render, masks, params)))
        for form in drops:
            drops[form].append(row[form])
        true_shapes.append(int(truth["kappa"]))
        print(json.dumps({"class": shot.class_name, "index": shot.index, "true_shape": int(truth["kappa"]),
                          **{form: {**dict(zip(names, np.round(row[form], 1).tolist())),
                                    "colour": round(float(min(row[form][len(names):], default=np.nan)), 1)}
                             for form in row}}), flush=True)
    summary = {}
    for form, rows in drops.items():
        shifts = np.asarray([row[:len(SHIFTS_MM)] for row in rows])
        shapes = np.asarray([row[len(SHIFTS_MM):len(SHIFTS_MM) + 3] for row in rows])
        washed = np.asarray([row[len(SHIFTS_MM) + 3] for row in rows])
        colours = np.asarray([min(row[len(SHIFTS_MM) + 4:], default=np.nan) for row in rows])
        own = np.arange(3)[None] == np.asarray(true_shapes)[:, None]
        wrong = np.where(own, np.inf, shapes).min(axis=1)                       # the nearest other shape
        summary[form] = {**{f"median drop {n}": round(float(np.median(shifts[:, i])), 1)
                            for i, n in enumerate(names[:len(SHIFTS_MM)])},
                         "median drop, nearest wrong shape": round(float(np.median(wrong)), 1),
                         "median drop, nearest wrong colour (same kind)": round(float(np.nanmedian(colours)), 1),
                         "median drop, true colour washed halfway out": round(float(np.median(washed)), 1),
                         "images where the washed-out colour beats the truth": int(np.sum(washed < 0)),
                         "images where a wrong colour beats the truth": int(np.sum(colours < 0)),
                         "images where a wrong shape beats the truth": int(np.sum(wrong < 0)),
                         "images where absent is cheaper than 2 mm": int(np.sum(shifts[:, 4] < shifts[:, 1])),
                         "images where absent is cheaper than 10 mm": int(np.sum(shifts[:, 4] < shifts[:, 3]))}
    print(json.dumps({"dataset": args.dataset, "probed": len(probe_half), "no_footprint_window": len(missed),
                      "summary": summary}, indent=1))


if __name__ == "__main__":
    main()
