"""The command line under attack (``tests/attack_cli.py``): every mistake a user makes ends refused
in one line or done right, never in a traceback, silence, a wrong result or lost data.

A few attacks that need no fitted model (one of each kind: labels that are not JSON, an empty folder,
a mesh shape without its mesh, a colour without its sRGB, a negative shot, a pose matrix that
disagrees, a 32-bit TIFF, outputs that are folders, a runaway resolution) run by default, on a tiny
generated benchmark; the rest, and every attack that needs a fitted model (infer, evaluate, fit, runs
in use), run with ``-m slow``."""
from __future__ import annotations

import importlib.util
import shutil
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


def _attack_cli():
    spec = importlib.util.spec_from_file_location("attack_cli", ROOT / "tests" / "attack_cli.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules["attack_cli"] = module            # its dataclasses look their module up by name
    spec.loader.exec_module(module)
    return module


attack_cli = _attack_cli()
ATTACKS = attack_cli.attacks()
FAST_NAMES = ("benchmark check: labels.json not JSON", "benchmark check: an empty folder",
              "benchmark check: a mesh shape without its mesh", "benchmark check: rgb null",
              "benchmark check: a negative shot", "benchmark check: object_to_world 10x the scale",
              "benchmark check: a 32-bit integer TIFF", "render: -o an existing directory",
              "render: --resolution 20000x20000", "fit: --light-falloff -1", "reproduce: --light-falloff -1")
FAST = [a for a in ATTACKS if a.name in FAST_NAMES]
SLOW = [a for a in ATTACKS if a.name not in FAST_NAMES]


@pytest.fixture(scope="module")
def source(tmp_path_factory):
    from .conftest import tiny_benchmark

    return tiny_benchmark(tmp_path_factory.mktemp("attack-source") / "fsclvr", seed=3)


@pytest.fixture(scope="module")
def work(source, tmp_path_factory):
    folder = tmp_path_factory.mktemp("attack")
    attack_cli.tiny_dataset(source, folder / "data")
    return folder


def test_every_fast_attack_is_one_of_the_scripts():
    assert len(FAST) == len(FAST_NAMES) and len(FAST) + len(SLOW) == len(ATTACKS)


@pytest.mark.parametrize("attack", FAST, ids=[a.name for a in FAST])
def test_a_mistake_on_ones_own_data_is_refused_in_one_line(work, attack):
    kind, message, _ = attack_cli.run(attack, work, slow=60.0)
    assert kind in attack_cli.CLEAN, f"{attack.name}: {kind}: {message}"


@pytest.fixture(scope="module")
def work_with_models(source, tmp_path_factory):
    """The scratch folder of the script's full run: the tiny data set, another one, a model fitted to
    the benchmark they were cut from (as the script copies a user's model: another fit than one of the
    tiny set, so that fitting the tiny set into it is a second data set) and a copy of it in another folder."""
    from mitsuba_p3.fit.model import fit_model
    from mitsuba_p3.fit.scene_opt import SceneOptConfig

    folder = tmp_path_factory.mktemp("attack-models")
    attack_cli.tiny_dataset(source, folder / "data")
    attack_cli.tiny_dataset(source, folder / "other-data", reverse=True)
    fit_model(source, folder / "model", scene_config=SceneOptConfig(
        resolution=(30, 40), pattern_size=16, epochs=2, material_passes=2, global_passes=2, refine_materials=False))
    shutil.copytree(folder / "model", folder / "other-model")
    (folder / "other-model" / "note.txt").write_text("another model")
    yield folder
    for process in attack_cli.BACKGROUND:
        process.kill()
        process.wait()


@pytest.mark.slow
@pytest.mark.parametrize("attack", SLOW, ids=[a.name for a in SLOW])
def test_every_other_mistake_is_refused_in_one_line_or_done_right(work_with_models, attack):
    kind, message, _ = attack_cli.run(attack, work_with_models, slow=60.0)
    assert kind in attack_cli.CLEAN, f"{attack.name}: {kind}: {message}"
