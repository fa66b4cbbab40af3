"""Would a conductor's tinted specular fit the path-traced metals better than Phong's white highlight?

The benchmarks' metals are rough conductors whose reflectance is the object's colour; Phong's
highlight is white. A tinted specular weight keeps the image affine in the material at a fixed
pose and shininess (the material bases of :mod:`mitsuba_p3.fit.materials`):

    I = c (k_a A + k_d D + k_t S) + k_s S + F

(k_t the colour-tinted specular, k_s the white one; a conductor is k_s = 0, a dielectric k_t = 0).
For every colour+material pair of the train split this refits the material exactly as the fit's
refinement does (alternating least squares, non-negative weights, each shininess of the grid), with
and without k_t, at the true geometry, and prints the object pixels' RMS per pair, the tint
k_t / (k_t + k_s), and the whole split's squared error with and without it.

    python experiments/probe_tinted_specular.py DATA_ROOT MODEL_FOLDER
"""
import argparse

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.materials import SHININESS_GRID, _ridge_nnls
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.fit.scene_opt import material_key
from mitsuba_p3.render import make_renderer


def fit(images: np.ndarray, bases: np.ndarray, start: np.ndarray, tinted: bool, iterations: int = 10):
    """Alternating least squares for one material at one shininess: (squared error over the images,
    over the object's pixels, the object's pixel count, colour, weights (k_a, k_d, k_s[, k_t]))."""
    A, D, S, F = (bases[..., i, :].reshape(-1, 3).astype(np.float64) for i in range(4))
    y = images.reshape(-1, 3).astype(np.float64) - F
    c = np.clip(np.asarray(start, np.float64), 1e-3, 1.0)
    for _ in range(iterations):
        columns = [(c * A).ravel(), (c * D).ravel(), S.ravel()] + ([(c * S).ravel()] if tinted else [])
        w = _ridge_nnls(np.stack(columns, axis=1), y.ravel())
        slope = w[0] * A + w[1] * D + (w[3] if tinted else 0.0) * S
        c = np.clip(np.sum(slope * (y - w[2] * S), axis=0) / np.maximum(np.sum(slope * slope, axis=0), 1e-12), 0, 1)
    slope = w[0] * A + w[1] * D + (w[3] if tinted else 0.0) * S
    squared = (np.clip(c * slope + w[2] * S + F, 0.0, 1.0) - (y + F)) ** 2
    on_object = (np.abs(A) + np.abs(D) + np.abs(S)).sum(axis=1) > 0
    return float(squared.sum()), float(squared[on_object].sum()), int(on_object.sum()), c, w


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("model")
    args = parser.parse_args()
    model = FittedModel(args.model)
    dataset = load_dataset(args.data, resolution=(120, 160))
    renderer = make_renderer(model.scene(), "mitsuba", height=120, width=160, shadows=True)
    groups: dict[str, list] = {}
    for shot in dataset.split("train"):
        groups.setdefault(material_key(shot), []).append(shot)
    totals, rows = {False: 0.0, True: 0.0}, []
    for key, shots in sorted(groups.items()):
        images = np.stack([dataset.image(s) for s in shots])
        params = [shot_params(s, model.materials) for s in shots]
        batch = {name: np.stack([np.asarray(p[name]) for p in params]) for name in params[0]}
        best = {}
        for alpha in SHININESS_GRID:
            batch["shininess"] = np.full(len(shots), alpha, np.float32)
            bases = renderer.render_bases(batch)
            for tinted in (False, True):
                result = fit(images, bases, model.materials[key]["colour"], tinted)
                if tinted not in best or result[0] < best[tinted][0][0]:
                    best[tinted] = (result, alpha)
        for tinted in (False, True):
            totals[tinted] += best[tinted][0][0]
        (plain, _), ((_, squared, pixels, _, w), alpha) = best[False], best[True]
        tint = w[3] / max(w[2] + w[3], 1e-9)
        rows.append((key, np.sqrt(plain[1] / plain[2] / 3), np.sqrt(squared / pixels / 3), tint))
        print(f"{key:22s} object RMS {rows[-1][1]:.4f} -> {rows[-1][2]:.4f}   tint {tint:.2f}   alpha {alpha:g}   "
              f"k_a k_d k_s k_t {np.round(w, 3).tolist()}", flush=True)
    print(f"train split squared error: white {totals[False]:.1f}, tinted {totals[True]:.1f} "
          f"(ratio {totals[True] / totals[False]:.4f})")
    for kind in ("metal", "rubber"):
        mine = [r for r in rows if r[0].endswith(kind)]
        if mine:
            print(f"{kind}: mean object RMS {np.mean([r[1] for r in mine]):.4f} -> {np.mean([r[2] for r in mine]):.4f}, "
                  f"tint median {np.median([r[3] for r in mine]):.2f} (range {min(r[3] for r in mine):.2f}-"
                  f"{max(r[3] for r in mine):.2f})")


if __name__ == "__main__":
    main()
