"""The Cycles benchmark renderer (CLEVR's assets through Blender): its worlds, refusals and images.

Rendering needs ``bpy`` (``pip install 'mitsuba-p3[blender]'``) and CLEVR's asset folder (``shared/clevr``
beside the repository, or ``MITSUBA_P3_CLEVR_ASSETS``); those tests skip without them.
"""
from __future__ import annotations

import json
import math
import os
from pathlib import Path

import numpy as np
import pytest

from mitsuba_p3.benchmarks import cycles
from mitsuba_p3.benchmarks.generate import generate
from mitsuba_p3.benchmarks.protocol import plan
from mitsuba_p3.errors import BenchmarkError

ASSETS = Path(os.environ.get("MITSUBA_P3_CLEVR_ASSETS", Path(__file__).resolve().parents[2] / "shared" / "clevr"))
needs_blender = pytest.mark.skipif(
    not (ASSETS / "base_scene.blend").is_file() or __import__("importlib").util.find_spec("bpy") is None,
    reason="needs bpy (pip install 'mitsuba-p3[blender]') and CLEVR's asset files")


def test_shipped_worlds_load_and_dark_dims_every_lamp():
    worlds = {v: cycles.load_world(cycles.world_file(v)) for v in ("fsclvr", "dark", "room")}
    assert worlds["dark"].lamp_strength == pytest.approx(0.25 * worlds["fsclvr"].lamp_strength)
    assert worlds["fsclvr"].clevr_ground and not worlds["room"].clevr_ground
    assert [s.texture for s in worlds["room"].surfaces][:2] == ["textures/wood.png", "textures/tiles.png"]


@pytest.mark.parametrize("body, message", [
    ('{"lamp_strength": 1}', 'with a "name"'),
    ('{"name": "w", "lamp_strength": "abc"}', "lamp_strength: must be a number"),
    ('{"name": "w", "samples": 0}', "samples: must be a number in [1"),
    ('{"name": "w", "colour": 1}', "unknown field(s) colour"),
    ('{"name": "w", "surfaces": [{"centre": [0, 0], "size": [1, 1]}]}', "centre: must be a list of 3"),
    ('{"name": "w", "surfaces": [{"centre": [0, 0, 0], "size": [1, 1], "texture": "../x.png"}]}',
     "texture must be a relative path"),
    ('{"name": "w", "surfaces": [{"centre": [0, 0, 0], "size": [1, 1], "texture": "none.png"}]}', "no texture"),
    ("[1, 2", "not a readable JSON world"),
    ('{"name": "w", "surfaces": 3}', "surfaces must be a list"),
])
def test_a_bad_world_is_refused_in_one_line(tmp_path, body, message):
    path = tmp_path / "w.cycles.json"
    path.write_text(body)
    with pytest.raises(BenchmarkError, match=None) as info:
        cycles.load_world(path)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_assets_are_checked_before_anything_is_written(tmp_path):
    (tmp_path / "assets").mkdir()
    with pytest.raises(BenchmarkError, match="missing base_scene.blend"):
        generate("fsclvr", tmp_path / "out", size="small", renderer="cycles", assets=tmp_path / "assets")
    with pytest.raises(BenchmarkError, match="needs --assets"):
        generate("fsclvr", tmp_path / "out", size="small", renderer="cycles")
    with pytest.raises(BenchmarkError, match="ood's objects are meshes"):
        generate("ood", tmp_path / "out", size="small", renderer="cycles", assets=ASSETS)
    with pytest.raises(BenchmarkError, match="unknown renderer"):
        generate("fsclvr", tmp_path / "out", size="small", renderer="blender")
    assert not (tmp_path / "out").exists()


def test_the_turn_carries_clevrs_camera_azimuth_onto_the_protocols():
    clevr_camera = (7.481, -6.508, 5.344)
    turned = cycles.rotate_z(clevr_camera, cycles.clevr_turn(clevr_camera))
    assert math.atan2(turned[1], turned[0]) == pytest.approx(math.atan2(-0.5, 0.0))
    assert np.hypot(*turned[:2]) == pytest.approx(np.hypot(*clevr_camera[:2]))


def _pixel(point, height, width):
    """Where the protocol camera sees a world point (row, column; pixel centres at integers)."""
    origin = np.array(cycles.CAMERA_ORIGIN)
    forward = -origin / np.linalg.norm(origin)
    right = np.cross(forward, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, forward)
    d = np.asarray(point) - origin
    tan_y = math.tan(math.radians(cycles.CAMERA_FOV_Y_DEG) / 2)
    tan_x = tan_y * width / height
    column = (1 + (d @ right) / (d @ forward) / tan_x) / 2 * width - 0.5
    row = (1 - (d @ up) / (d @ forward) / tan_y) / 2 * height - 0.5
    return int(round(row)), int(round(column))


@needs_blender
def test_a_small_cycles_benchmark_has_the_protocols_labels_objects_where_they_stand_and_resumes(tmp_path):
    from PIL import Image

    out = tmp_path / "fsclvr-cycles"
    generate("fsclvr", out, size="small", spp=4, renderer="cycles", assets=ASSETS)
    labels = json.loads((out / "labels.json").read_text())
    planned = plan("fsclvr", 0, "small")
    assert labels["renderer"] == "cycles" and labels["resolution"] == [120, 160]
    assert [r["file"] for r in labels["images"]] == [p.file for p in planned]
    assert [r["pose"]["x"] for r in labels["images"]] == [p.pose.x for p in planned]
    assert set(labels["images"][0]["lights"]) == {"light_key_position", "light_fill_position",
                                                  "light_back_position"}
    # each object stands where its label says: the pixels unlike the floor around its projected centre (the
    # object and its shadow) are centred on it, within a pixel or two
    offsets = []
    for record in labels["images"]:
        image = np.asarray(Image.open(out / record["file"]).convert("RGB"), dtype=float)
        row, col = _pixel([record["pose"][k] for k in "xyz"], 120, 160)
        floor = np.median(image.reshape(-1, 3), axis=0)
        unlike = np.abs(image - floor).sum(axis=-1) > 60
        unlike[:max(row - 15, 0)] = unlike[row + 16:] = False
        unlike[:, :max(col - 15, 0)] = unlike[:, col + 16:] = False
        rows, cols = np.nonzero(unlike)
        assert len(rows) > 3, record["file"]
        offsets.append(np.hypot(np.median(rows) - row, np.median(cols) - col))
    assert np.median(offsets) < 1.5, offsets
    # resume: a lost image is rendered again, the others are kept as they are
    kept = out / labels["images"][1]["file"]
    before = kept.stat().st_mtime_ns
    (out / labels["images"][0]["file"]).unlink()
    generate("fsclvr", out, size="small", spp=4, renderer="cycles", assets=ASSETS)
    assert (out / labels["images"][0]["file"]).is_file() and kept.stat().st_mtime_ns == before
    with pytest.raises(BenchmarkError, match="different benchmark"):
        generate("fsclvr", out, size="small", spp=8, renderer="cycles", assets=ASSETS)
    assert not list(out.rglob(".*partial*"))
