"""Does the correlated-noise model whiten residuals it was not fitted on? Spectra per benchmark, a figure.

For each benchmark, the fitted model's train residuals (true geometry, fitted materials, the fit's
hard shadows) on the windows the sampler scores (:data:`~mitsuba_p3.fit.noise.SCORING_WINDOW`,
centred on the object) are split by class into two halves. The spectral noise form
(:func:`~mitsuba_p3.fit.noise.fit_spectra`, the fit's own shrinkage) is fitted on one half and
applied to the other, and the other way round. Printed per benchmark, on the held-out windows:

- the raw residuals' correlation area and their low-to-high frequency power ratio;
- the whitened residuals' variance (1 if the spectrum's level transfers), correlation area (1 if the
  field's shape does) and low-to-high power ratio (1 if white).

The figure (``--figure``) draws, per benchmark, the radially averaged power of the raw held-out
windows, of their whitened version and of white noise of the raw residuals' variance (what the
default independent Gaussian assumes). Whitening held-out windows is a check that can fail: a
spectrum that only memorised its own windows leaves the other half's low frequencies loud.

    python experiments/plot_noise_spectra.py --pairs fsclvr=data/fsclvr-lo:data/models/fsclvr-lo,... \
        --figure results/noise-forms/spectra.png
"""
import argparse

import numpy as np

from mitsuba_p3.fit.noise import (SCORING_WINDOW, SPECTRAL_SHRINK, correlation_area, fit_spectra, object_pixels,
                                  whiten_numpy, window_around)


def residual_windows(data_dir: str, model_dir: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The train split's residual windows (N, h, w, 3), their object masks (N, h, w) and class indices (N,)."""
    from mitsuba_p3.benchmarks.dataset import load_dataset
    from mitsuba_p3.fit.model import FittedModel, empty_render, render_train_split

    model, data = FittedModel(model_dir), load_dataset(data_dir)
    height, width = data.resolution
    observations, renders = render_train_split(model, data)
    empty = empty_render(model, height, width, True)
    residual = observations.astype(np.float64) - renders
    found = object_pixels(renders, empty)
    h, w = SCORING_WINDOW
    corners = [window_around(found[n], (h, w)) for n in range(len(residual))]
    windows = np.stack([residual[n, t:t + h, l:l + w] for n, (t, l) in enumerate(corners)])
    masks = np.stack([found[n, t:t + h, l:l + w] for n, (t, l) in enumerate(corners)])
    names = sorted({s.cls.name for s in data.split("train")})
    classes = np.array([names.index(s.cls.name) for s in data.split("train")])
    return windows, masks, classes


def radial_power(windows: np.ndarray, bins: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """(frequency, mean power) of windows (N, h, w, 3): the orthonormal periodogram averaged over images,
    channels and rings of |k| (cycles per pixel)."""
    h, w = windows.shape[1:3]
    power = np.mean(np.abs(np.fft.fft2(windows, axes=(1, 2), norm="ortho")) ** 2, axis=(0, 3))
    radius = np.hypot(*np.meshgrid(np.fft.fftfreq(h), np.fft.fftfreq(w), indexing="ij"))
    edges = np.linspace(0.0, 0.5 * np.sqrt(2), bins + 1)
    which = np.clip(np.digitize(radius, edges) - 1, 0, bins - 1)
    count = np.bincount(which.ravel(), minlength=bins)
    mean = np.bincount(which.ravel(), power.ravel(), minlength=bins) / np.maximum(count, 1)
    keep = count > 0
    return (0.5 * (edges[:-1] + edges[1:]))[keep], mean[keep]


def low_to_high(windows: np.ndarray) -> float:
    """Mean power of the lowest frequencies (|k| < 0.06 cycles/pixel) over that of the upper half (> 0.25)."""
    freq, power = radial_power(windows, bins=24)
    return float(power[freq < 0.06].mean() / power[freq > 0.25].mean())


def held_out(windows: np.ndarray, masks: np.ndarray, classes: np.ndarray,
             shrink: float = SPECTRAL_SHRINK) -> tuple[np.ndarray, np.ndarray]:
    """(raw, whitened) held-out windows: each half of the classes whitened by the spectrum of the other,
    shrunk by ``shrink`` towards white noise."""
    half = classes % 2 == 0
    raw, white = [], []
    for fit_on in (half, ~half):
        spectra, _, _ = fit_spectra(windows[fit_on], masks[fit_on], [SCORING_WINDOW], shrink)
        spectrum = spectra[SCORING_WINDOW].astype(np.float64)
        raw.append(windows[~fit_on])
        white.append(whiten_numpy(windows[~fit_on], spectrum))
    return np.concatenate(raw), np.concatenate(white)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pairs", required=True,
                        help="NAME=DATA:MODEL,... benchmark folders and their fitted models")
    parser.add_argument("--figure", help="write the spectra figure here (PNG)")
    args = parser.parse_args()
    curves = {}
    for item in args.pairs.split(","):
        name, paths = item.split("=", 1)
        data_dir, model_dir = paths.split(":", 1)
        windows, masks, classes = residual_windows(data_dir, model_dir)
        raw, white = held_out(windows, masks, classes)
        _, pure = held_out(windows, masks, classes, shrink=0.0)
        print(f"{name}: {len(windows)} train windows {SCORING_WINDOW[0]}x{SCORING_WINDOW[1]}, "
              f"{len(set(classes))} classes, spectrum fitted on half the classes, applied to the other")
        print(f"  raw held-out:      RMS {np.sqrt(np.mean(raw ** 2)):.4f}  correlation area "
              f"{correlation_area(raw):6.1f} px  low/high power {low_to_high(raw):8.1f}")
        print(f"  whitened held-out: variance {np.mean(white ** 2):.3f}  correlation area "
              f"{correlation_area(white):6.1f} px  low/high power {low_to_high(white):8.2f}  "
              f"(shrink {SPECTRAL_SHRINK:g}, the fit's)")
        print(f"  whitened held-out: variance {np.mean(pure ** 2):.3f}  correlation area "
              f"{correlation_area(pure):6.1f} px  low/high power {low_to_high(pure):8.2f}  (shrink 0, the pure field)")
        curves[name] = (radial_power(raw), radial_power(white), radial_power(pure), float(np.mean(raw ** 2)))
    if args.figure:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, len(curves), figsize=(3.6 * len(curves), 3.3), squeeze=False)
        for ax, (name, ((f, p), (fw, pw), (fp, pp), variance)) in zip(axes[0], curves.items()):
            ax.loglog(f, p / variance, "o-", label="raw residual / its variance")
            ax.loglog(fw, pw, "s-", label=f"whitened, shrink {SPECTRAL_SHRINK:g} (held-out classes)")
            ax.loglog(fp, pp, "^-", label="whitened, shrink 0 (held-out classes)")
            ax.set_xticks([0.02, 0.05, 0.1, 0.2, 0.5], ["0.02", "0.05", "0.1", "0.2", "0.5"])
            ax.minorticks_off()
            ax.axhline(1.0, color="k", lw=0.8, ls="--", label="white noise (independent Gaussian)")
            ax.set_title(name)
            ax.set_xlabel("spatial frequency |k| (cycles / pixel)")
        axes[0, 0].set_ylabel("power, relative to white")
        axes[0, 0].legend(fontsize=7)
        fig.suptitle(f"Residual spectra on {SCORING_WINDOW[0]}x{SCORING_WINDOW[1]} scoring windows, train split")
        fig.tight_layout()
        fig.savefig(args.figure, dpi=120)
        print(f"figure: {args.figure}")


if __name__ == "__main__":
    main()
