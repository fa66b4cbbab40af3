"""Copy the benchmark contact sheets and training-stage figures into docs/figures/ (README).

Expects data/VARIANT/ (benchmark folders) and data/models/VARIANT/ (fitted models, with
`python scripts/plot_fit.py data/models/VARIANT` run); makes any missing contact sheet.
Photographic figures become JPEG, plots stay PNG, all at most 1400 px wide. Usage:

    python scripts/make_docs_figures.py [--data data] [--out docs/figures]
"""
from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

from PIL import Image

PHOTOS = ("progress", "prior_predictive")
PLOTS = ("materials", "gmm_priors", "reparametrisation", "loss")


def save(source: Path, target: Path, width: int = 1400) -> Path:
    image = Image.open(source).convert("RGB")
    if image.size[0] > width:
        image = image.resize((width, round(image.size[1] * width / image.size[0])), Image.LANCZOS)
    target.parent.mkdir(parents=True, exist_ok=True)
    if target.suffix == ".jpg":
        image.save(target, quality=86)
    else:
        image.save(target, optimize=True)
    return target


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=Path("docs/figures"))
    args = parser.parse_args()
    for variant in ("fsclvr", "dark", "room", "ood"):
        folder = args.data / variant
        if not (folder / "labels.json").is_file():
            continue
        sheet = args.data / f"{variant}-sheet.png"
        if not sheet.is_file():
            shown = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "benchmark", "show", str(folder), "-o",
                                    str(sheet)], capture_output=True, text=True)
            if shown.returncode != 0:
                print(f"skipping {variant}: {shown.stderr.splitlines()[0]}")
                continue
        print(save(sheet, args.out / f"{variant}-sheet.jpg"))
        figures = args.data / "models" / variant / "figures"
        for name in PHOTOS + PLOTS:
            if (figures / f"{name}.png").is_file():
                suffix = ".jpg" if name in PHOTOS else ".png"
                print(save(figures / f"{name}.png", args.out / f"fit-{variant}-{name}{suffix}", 1200))


if __name__ == "__main__":
    main()
