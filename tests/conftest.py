"""Shared fixtures: the repo's scenes at small resolutions (tests stay fast)."""
from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

ROOT = Path(__file__).resolve().parents[1]
SCENES = ROOT / "scenes"
VARIANTS = ("fsclvr", "dark", "room", "ood")


@pytest.fixture(scope="package")
def mi():
    from mitsuba_p3.backend import mitsuba
    from mitsuba_p3.render import phong  # noqa: F401  (registers the phong plugins)

    return mitsuba()


@pytest.fixture
def scene():
    from mitsuba_p3.scene import load_scene

    return load_scene(SCENES / "fsclvr.xml")


@pytest.fixture
def room_scene():
    from mitsuba_p3.scene import load_scene

    return load_scene(SCENES / "room.xml")


def random_object_params(rng: np.random.Generator, batch: int) -> dict[str, np.ndarray]:
    """Object parameters for a batch of plausible scenes (every shape class)."""
    return {
        "shift": rng.uniform(-0.06, 0.06, (batch, 2)).astype(np.float32),
        "theta": rng.uniform(-np.pi, np.pi, batch).astype(np.float32),
        "scale": rng.uniform(0.015, 0.04, (batch, 3)).astype(np.float32),
        "kappa": (np.arange(batch) % 3).astype(np.int32),
        "colour": rng.uniform(0.1, 0.9, (batch, 3)).astype(np.float32),
        "ambient": rng.uniform(0.05, 0.3, batch).astype(np.float32),
        "diffuse": rng.uniform(0.3, 0.9, batch).astype(np.float32),
        "specular": rng.uniform(0.0, 0.8, batch).astype(np.float32),
        "shininess": rng.uniform(2.0, 40.0, batch).astype(np.float32),
    }


def tiny_benchmark(folder: Path, seed: int) -> Path:
    """The small fsclvr benchmark at 30x40 with 8 samples per pixel, generated into ``folder`` (seconds)."""
    from mitsuba_p3.benchmarks.generate import generate

    generate("fsclvr", folder, seed=seed, size="small", resolution=(30, 40), spp=8)
    return folder

