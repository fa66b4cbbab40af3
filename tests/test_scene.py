"""Scene XML: round trips, overrides, Mitsuba's own loader, and clear errors."""
from __future__ import annotations

import shutil

import numpy as np
import pytest

from mitsuba_p3.errors import SceneError
from mitsuba_p3.scene import MATERIALS, PhongMaterial, load_scene, save_scene

from .conftest import SCENES, VARIANTS


@pytest.mark.parametrize("variant", VARIANTS)
def test_variants_load_and_round_trip(variant, tmp_path):
    scene = load_scene(SCENES / f"{variant}.xml")
    assert scene.lights and scene.object.shape == "sphere"
    path = save_scene(scene, tmp_path / f"{variant}.xml")
    again = load_scene(path)
    for key, value in scene.params().items():
        np.testing.assert_allclose(again.params()[key], value, atol=2e-3 if key == "floor_pattern" else 1e-6,
                                   err_msg=key)


@pytest.mark.parametrize("variant", VARIANTS)
def test_variants_are_genuine_mitsuba_scenes(mi, variant):
    scene = mi.load_file(str(SCENES / f"{variant}.xml"), shape="cylinder")
    image = mi.render(scene, spp=1).numpy()
    assert image.shape == (480, 640, 3) and 0.05 < image.mean() < 0.9


def test_overrides_change_the_object():
    scene = load_scene(SCENES / "fsclvr.xml", {"shape": "cube", "shift_x": "0.05", "theta_deg": "90",
                                                "scale": "0.01, 0.02, 0.03", "colour": "0.1, 0.2, 0.3"})
    obj = scene.object
    assert obj.shape == "cube"
    np.testing.assert_allclose(obj.shift, [0.05, 0.0])
    assert obj.theta == pytest.approx(np.pi / 2)
    np.testing.assert_allclose(obj.scale, [0.01, 0.02, 0.03])
    np.testing.assert_allclose(obj.material.colour, [0.1, 0.2, 0.3])


def test_editing_the_xml_changes_the_scene(tmp_path):
    text = (SCENES / "fsclvr.xml").read_text()
    edited = text.replace('<point name="position" value="0.3, -0.35, 0.45" />',
                          '<point name="position" value="0.1, 0.2, 0.6" />')
    assert edited != text
    (tmp_path / "edited.xml").write_text(edited)
    scene = load_scene(tmp_path / "edited.xml")
    np.testing.assert_allclose(scene.lights[0].position, [0.1, 0.2, 0.6])


def test_named_materials():
    metal = PhongMaterial.named("cyan", "metal")
    np.testing.assert_allclose(metal.colour, np.array([41, 208, 208]) / 255)
    assert (metal.ambient, metal.diffuse, metal.specular, metal.shininess) == MATERIALS["metal"]
    with pytest.raises(SceneError, match="unknown material 'wood'"):
        PhongMaterial.named("red", "wood")
    with pytest.raises(SceneError, match="unknown colour"):
        PhongMaterial.named("mauve", "metal")


def _copy_scene(tmp_path, variant="room"):
    shutil.copy(SCENES / f"{variant}.xml", tmp_path / "scene.xml")
    shutil.copytree(SCENES / "textures", tmp_path / "textures")
    return tmp_path / "scene.xml"


@pytest.mark.parametrize("mutate, message", [
    (lambda t: t.replace("</scene>", ""), "malformed XML"),
    (lambda t: t.replace('<default name="shape" value="sphere" />', '<default name="shape" value="cone" />'),
     "unknown shape 'cone'"),
    (lambda t: t.replace('value="0.035, 0.035, 0.035"', 'value="-0.035, 0.035, 0.035"'), "scale must be positive"),
    (lambda t: t.replace("textures/wood.png", "textures/missing.png"), "missing.png does not exist"),
    (lambda t: t.replace('<float name="diffuse" value="$diffuse" />', '<float name="diffuse" value="nan" />'),
     "finite"),
    (lambda t: t.replace('<rotate z="1"', '<rotate x="1"'), "only rotate about z"),
])
def test_bad_scene_files_raise_clear_errors(tmp_path, mutate, message):
    path = _copy_scene(tmp_path)
    path.write_text(mutate(path.read_text()))
    with pytest.raises(SceneError, match=message) as info:
        load_scene(path)
    assert str(path) in str(info.value)


def test_unknown_override_is_rejected():
    with pytest.raises(SceneError, match="cannot set 'colr'"):
        load_scene(SCENES / "fsclvr.xml", {"colr": "1,0,0"})


def test_missing_file():
    with pytest.raises(SceneError, match="no such scene file"):
        load_scene(SCENES / "nope.xml")
