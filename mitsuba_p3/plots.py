"""Figures a person looks at: contact sheets and image grids (matplotlib, no display needed)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a figure atomically (a killed run never leaves half a PNG) and close it."""
    plt = _pyplot()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(path.stem + ".tmp" + path.suffix)
    fig.savefig(tmp, dpi=dpi, bbox_inches="tight")
    plt.close(fig)
    tmp.replace(path)
    return path


def image_grid(images: Sequence[np.ndarray], titles: Sequence[str], path: str | Path,
               columns: int = 6, title: str | None = None, cell: float = 2.0) -> Path:
    """Images in a grid, each with a small title underneath."""
    plt = _pyplot()
    rows = max(1, -(-len(images) // columns))
    aspect = images[0].shape[0] / images[0].shape[1] if images else 0.75
    fig, axes = plt.subplots(rows, columns, figsize=(cell * columns, cell * aspect * rows + 0.35 * rows + 0.4),
                             squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, image, text in zip(axes.flat, images, titles):
        ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        ax.set_title(text, fontsize=7, y=-0.16)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def contact_sheet(dataset, path: str | Path, columns: int = 8) -> Path:
    """One labelled shot (shot 0) per class of a data set, train classes first."""
    images, titles = [], []
    for split in ("train", "test"):
        for name in dataset.classes(split):
            shot = dataset.shots_of(name)[0]
            images.append(dataset.image(shot))
            titles.append(f"{split}: {name}")
    title = f"{dataset.variant}: {len(titles)} classes ({dataset.root})"
    return image_grid(images, titles, path, columns=min(columns, len(images)), title=title)
