"""Both Mitsuba render paths against the stored reference renders (tests/references/).

Regenerate them with `python scripts/make_references.py` after a deliberate change
to the Phong model, and look at tests/references.png before committing.
"""
from __future__ import annotations

import json

import numpy as np
import pytest

from mitsuba_p3.images import read_png
from mitsuba_p3.render import make_renderer
from mitsuba_p3.scene import load_scene

from .conftest import ROOT

REFERENCES = ROOT / "tests" / "references"
MANIFEST = json.loads((REFERENCES / "cases.json").read_text())
CASES = MANIFEST["cases"]


def _compare(image: np.ndarray, reference: np.ndarray, name: str) -> None:
    assert image.shape == reference.shape, name
    diff = np.abs(image - reference).max(axis=2)
    # References are 8-bit PNGs: half a code value of quantisation, plus silhouette pixels.
    assert (diff > 2 / 255).mean() <= 0.01, f"{name}: {(diff > 2 / 255).mean():.2%} of pixels differ"
    assert diff.mean() < 1 / 255, f"{name}: mean difference {diff.mean() * 255:.2f}/255"


@pytest.mark.parametrize("case", CASES, ids=[c["name"] for c in CASES])
def test_fast_renderer_matches_reference(case):
    scene = load_scene(ROOT / case["scene"], case["overrides"])
    renderer = make_renderer(scene, height=MANIFEST["height"], width=MANIFEST["width"], shadows=case["shadows"])
    _compare(renderer.render(), read_png(REFERENCES / f"{case['name']}.png"), case["name"])


@pytest.mark.parametrize("case", CASES[::5], ids=[c["name"] for c in CASES[::5]])
def test_mitsuba_integrator_matches_reference(case):
    import sys

    sys.path.insert(0, str(ROOT / "scripts"))
    from make_references import render_reference

    _compare(render_reference(case), read_png(REFERENCES / f"{case['name']}.png"), case["name"])


def test_references_are_not_blank():
    """Guards the guard: every reference shows an object distinct from the floor."""
    for case in CASES:
        image = read_png(REFERENCES / f"{case['name']}.png")
        centre = image[20:40, 30:50].mean(axis=(0, 1))
        corner = image[:8, :8].mean(axis=(0, 1))
        assert np.abs(centre - corner).max() > 0.05, case["name"]
