"""Regenerate the reference renders under tests/references/.

Each reference is rendered by Mitsuba's own scene loading (``mi.load_file`` on
tests/references/closeup.xml -- scenes/fsclvr.xml with the camera moved close so
the object fills the frame -- through shape groups, an instance and Embree) with the project's
``phong_integrator``, at 60x80, for every shape x a few materials x shadows
off/on. tests/test_references.py renders the same cases with both render paths
and compares. A contact sheet (references.png) is written for a person to look
at before committing. Usage:

    python scripts/make_references.py [--out tests/references]
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
HEIGHT, WIDTH = 60, 80

# name -> scene <default> overrides; every shape under three materials, yawed (cube and
# cylinder also stretched; the sphere stays round).
MATERIAL_CASES = {
    "red-rubber": {"colour": "0.678, 0.137, 0.137", "ambient": "0.1", "diffuse": "0.9",
                   "specular": "0.1", "shininess": "4"},
    "blue-metal": {"colour": "0.165, 0.294, 0.843", "ambient": "0.1", "diffuse": "0.4",
                   "specular": "0.9", "shininess": "40"},
    "yellow-glossy": {"colour": "1, 0.933, 0.2", "ambient": "0.2", "diffuse": "0.7",
                      "specular": "0.5", "shininess": "12"},
}
CLOSEUP = "tests/references/closeup.xml"
POSE = {"shift_x": "0.015", "shift_y": "-0.01", "theta_deg": "30", "scale": "0.045, 0.03, 0.035"}


def cases() -> list[dict]:
    out = []
    for shape in ("sphere", "cube", "cylinder"):
        for material, values in MATERIAL_CASES.items():
            for shadows in (False, True):
                out.append({"name": f"{shape}-{material}-{'shadows' if shadows else 'noshadows'}",
                            "scene": CLOSEUP, "shadows": shadows,
                            "overrides": {"shape": shape, **POSE, **values,
                                          **({"scale": "0.035"} if shape == "sphere" else {})}})
    return out


def write_closeup_scene() -> Path:
    """fsclvr's world seen from 20 cm away, so that a 60x80 image shows the object's shading."""
    from mitsuba_p3.scene import load_scene, save_scene

    scene = load_scene(ROOT / "scenes" / "fsclvr.xml")
    scene.camera.origin = np.array([0.0, -0.16, 0.12])
    scene.camera.target = np.array([0.0, 0.0, 0.03])
    scene.camera.height, scene.camera.width = HEIGHT, WIDTH
    return save_scene(scene, ROOT / CLOSEUP, "fsclvr's world, close-up camera (reference renders)")


def render_reference(case: dict) -> np.ndarray:
    """Render one case with Mitsuba's loader and the phong_integrator."""
    from mitsuba_p3.backend import mitsuba

    mi = mitsuba()
    scene = mi.load_file(str(ROOT / case["scene"]), **case["overrides"])
    integrator = mi.load_dict({"type": "phong_integrator", "shadows": case["shadows"]})
    return mi.render(scene, integrator=integrator).numpy()


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", default=str(ROOT / "tests" / "references"))
    args = parser.parse_args()
    from mitsuba_p3.images import write_png

    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    write_closeup_scene()
    images = []
    for case in cases():
        image = render_reference(case)
        write_png(out / f"{case['name']}.png", image)
        images.append(image)
        print(case["name"])
    (out / "cases.json").write_text(json.dumps({"height": HEIGHT, "width": WIDTH, "cases": cases()}, indent=1))
    rows = [np.concatenate(images[i:i + 6], axis=1) for i in range(0, len(images), 6)]
    write_png(out.parent / "references.png", np.concatenate(rows, axis=0))


if __name__ == "__main__":
    main()
