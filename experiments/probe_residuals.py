"""Where the fitted model's train residuals are, and whether a smooth field explains them.

At the train split's true geometry with the fitted materials and the fit's hard shadows, the squared
residual (image - render) is split by region: the object's edge (a pixel either side of its
outline), the object's interior (and that per material), the floor the object changes (its shadow,
where the render differs from the empty floor) and the rest of the floor. Then, on the windows the
sampler scores (:data:`~mitsuba_p3.fit.noise.SCORING_WINDOW`, centred on the object), polynomial
fields of growing degree are projected out per channel, as a marginalised smooth illumination
nuisance would: the RMS left says how much of the residual is smooth at the window's scale.

    python experiments/probe_residuals.py DATA_ROOT MODEL_FOLDER
"""
import argparse

import numpy as np
from scipy import ndimage

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, empty_render, render_train_split
from mitsuba_p3.fit.noise import SCORING_WINDOW, correlation_area, object_pixels, window_around


def outline(inside: np.ndarray) -> np.ndarray:
    """The pixels either side of a mask's boundary (H, W)."""
    return ndimage.binary_dilation(inside) & ~ndimage.binary_erosion(inside)


def regions(renders: np.ndarray, empty: np.ndarray, ids: np.ndarray) -> dict[str, np.ndarray]:
    obj = ids == 2
    edge = np.stack([outline(o) for o in obj])
    changed = (np.abs(renders - empty).sum(-1) > 0.01) & ~obj & ~edge
    return {"edge": edge, "interior": obj & ~edge, "floor the object changes": changed,
            "rest of the floor": ~obj & ~edge & ~changed}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data")
    parser.add_argument("model")
    args = parser.parse_args()
    from mitsuba_p3.fit.model import shot_params
    from mitsuba_p3.render import make_renderer

    model, data = FittedModel(args.model), load_dataset(args.data)
    height, width = data.resolution
    observations, renders = render_train_split(model, data)
    empty = empty_render(model, height, width, True)
    renderer = make_renderer(model.scene(), "mitsuba", height=height, width=width, shadows=True)
    shots = data.split("train")
    ids = np.stack([renderer.surface_ids(shot_params(s, model.materials)) for s in shots])
    residual = observations.astype(np.float64) - renders
    squared = (residual ** 2).sum(-1)
    total = squared.sum()
    print(f"{data.variant}: {len(shots)} train images, residual RMS {np.sqrt(np.mean(residual ** 2)):.4f}, "
          f"correlation area {correlation_area(residual):.1f} px")
    masks = regions(renders, empty, ids)
    metal = np.array([s.cls.material == "metal" for s in shots])[:, None, None]
    masks["interior, metal"] = masks["interior"] & metal
    masks["interior, rubber"] = masks["interior"] & ~metal
    for name, mask in masks.items():
        print(f"  {name:26s} share of squared error {squared[mask].sum() / total:.3f}  "
              f"pixels/image {mask.sum() / len(shots):7.0f}  RMS {np.sqrt(squared[mask].mean() / 3):.4f}")
    # is the far floor's residual white (the path tracer's Monte Carlo noise) or a field?
    far = masks["rest of the floor"]
    pairs = far[:, :, 1:] & far[:, :, :-1]
    right = (residual[:, :, 1:] * residual[:, :, :-1]).sum(-1)[pairs].mean()
    print(f"  rest of the floor: correlation of horizontal neighbours {right / (squared[far].mean()):.3f} "
          "(0: white noise, 1: a smooth field)")
    h, w = SCORING_WINDOW
    found = object_pixels(renders, empty)
    corners = [window_around(found[n], (h, w)) for n in range(len(shots))]
    windows = np.stack([residual[n, t:t + h, l:l + w] for n, (t, l) in enumerate(corners)]).reshape(len(shots), -1, 3)
    yy, xx = np.mgrid[0:h, 0:w]
    y, x = (yy - (h - 1) / 2) / (h / 2), (xx - (w - 1) / 2) / (w / 2)
    print(f"  scoring windows {h}x{w}: RMS left after projecting out polynomial fields per channel")
    for degree in (0, 1, 2, 4, 6):
        basis, _ = np.linalg.qr(np.stack([(x ** i * y ** j).ravel() for i in range(degree + 1)
                                          for j in range(degree + 1 - i)], 1))
        rest = windows - np.einsum("pk,nkc->npc", basis, np.einsum("pk,npc->nkc", basis, windows))
        print(f"    degree {degree} ({basis.shape[1]:2d} functions): RMS {np.sqrt(np.mean(rest ** 2)):.4f} "
              f"(explained {1 - np.mean(rest ** 2) / np.mean(windows ** 2):.1%})")


if __name__ == "__main__":
    main()
