"""The `mitsuba-p3 render` command: it renders, it follows overrides, and bad input is one line."""
from __future__ import annotations

import shutil
import subprocess
import sys

import numpy as np
import pytest

from mitsuba_p3.images import read_png

from .conftest import SCENES


def run(*args, cwd=None):
    return subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", *map(str, args)], capture_output=True,
                          text=True, timeout=300, cwd=cwd)


def test_render_writes_png_and_follows_overrides(tmp_path):
    plain = run("render", SCENES / "fsclvr.xml", "--resolution", "60x80", "-o", tmp_path / "a.png")
    assert plain.returncode == 0, plain.stderr
    changed = run("render", SCENES / "fsclvr.xml", "--resolution", "60x80", "--shape", "cube", "--color", "green",
                  "--material", "metal", "--shift", "0.03,0.01", "--theta", "20", "--scale", "small",
                  "--shadows", "-o", tmp_path / "b.png")
    assert changed.returncode == 0, changed.stderr
    a, b = read_png(tmp_path / "a.png"), read_png(tmp_path / "b.png")
    assert a.shape == b.shape == (60, 80, 3)
    assert np.abs(a - b).max() > 0.1


def _broken(tmp_path, old, new):
    shutil.copy(SCENES / "room.xml", tmp_path / "scene.xml")
    shutil.copytree(SCENES / "textures", tmp_path / "textures")
    path = tmp_path / "scene.xml"
    path.write_text(path.read_text().replace(old, new))
    return path


@pytest.mark.parametrize("case", ["malformed", "shape", "material", "scale", "texture", "resolution", "geometry",
                                  "output"])
def test_bad_input_is_one_error_line(tmp_path, case):
    scene = SCENES / "fsclvr.xml"
    extra = []
    if case == "malformed":
        scene = _broken(tmp_path, "</scene>", "")
    elif case == "shape":
        extra = ["--shape", "pyramid"]
    elif case == "material":
        extra = ["--material", "velvet"]
    elif case == "scale":
        extra = ["--scale=-0.02"]
    elif case == "texture":
        scene = _broken(tmp_path, "textures/wood.png", "textures/nowhere.png")
    elif case == "resolution":
        extra = ["--resolution", "120by160"]
    elif case == "geometry":        # other geometry in a shape group: it was ignored, exit 0
        scene = _broken(tmp_path, '<shape type="sphere">', '<shape type="dodecahedron">')
    output = tmp_path / "out.png"
    if case == "output":            # -o out.exr wrote PNG bytes under that name
        output = tmp_path / "out.exr"
    done = run("render", scene, *extra, "-o", output)
    assert done.returncode != 0
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:"), done.stderr
    assert not output.exists()


def test_sampler_auto_follows_the_noise_model():
    """--sampler auto: SMC under a fitted noise model, MH under the paper's (and at an explicit sigma)."""
    from mitsuba_p3.cli.pipeline_commands import choose_sampler
    from mitsuba_p3.errors import ConfigError
    from mitsuba_p3.infer.mcmc import SamplerConfig
    from mitsuba_p3.infer.smc import SMCConfig

    mh = SamplerConfig(seed=3)
    assert choose_sampler("auto", mh, 16, "fitted", None) == SMCConfig(particles=16, seed=3)
    assert choose_sampler("auto", mh, 16, "robust", None) == SMCConfig(particles=16, seed=3)
    assert choose_sampler("auto", mh, 16, "paper", None) is mh
    assert choose_sampler("auto", mh, 16, "fitted", 0.35) is mh
    assert choose_sampler("smc", mh, 16, "paper", None) == SMCConfig(particles=16, seed=3)
    with pytest.raises(ConfigError, match="choose auto, smc or mh"):
        choose_sampler("nuts", mh, 16, "paper", None)


def test_every_sampler_field_is_reachable_with_set_and_config(tmp_path):
    """--set SAMPLER.FIELD=VALUE and --config FILE reach every field of both sampler configs (each field
    set to a value other than its default, read back); unknown fields, malformed values and a setting for
    the sampler not chosen are refused; the config's own checks still run."""
    import dataclasses

    from mitsuba_p3.cli.settings import apply_settings
    from mitsuba_p3.errors import ConfigError
    from mitsuba_p3.infer.mcmc import SamplerConfig
    from mitsuba_p3.infer.smc import SMCConfig
    from mitsuba_p3.infer.smc_moves import SYMMETRY_MOVES

    choices = {"symmetry": SYMMETRY_MOVES}          # a text field's values
    other = {bool: lambda v: str(not v).lower(), int: lambda v: str(v + 2), float: lambda v: str(v * 0.9 if v else 0.1)}
    # (from an SMC without the wide start, which persistent sampling and waste-free SMC exclude)
    for config, prefix in ((SMCConfig(wide_steps=0), "smc"), (SamplerConfig(), "mh")):
        for field in dataclasses.fields(config):
            value = getattr(config, field.name)
            if isinstance(value, tuple):
                text, expected = "40x48", (40, 48)
            elif isinstance(value, str):
                text = expected = next(choice for choice in choices[field.name] if choice != value)
            else:
                text = other[type(value)](value)
                expected = type(value)(text == "true") if isinstance(value, bool) else type(value)(text)
            changed = apply_settings(config, [f"{prefix}.{field.name}={text}"])
            assert getattr(changed, field.name) == expected, field.name
    with pytest.raises(ConfigError, match="symmetry"):
        apply_settings(SMCConfig(), ["smc.symmetry=sideways"])
    (tmp_path / "settings.json").write_text('{"smc": {"islands": 3, "window": null, "persistent": true}}')
    from_file = apply_settings(SMCConfig(wide_steps=0), ["smc.islands=4"], tmp_path / "settings.json")
    assert (from_file.islands, from_file.window, from_file.persistent) == (4, None, True)   # --set after the file
    for bad, needle in ((["smc.nope=1"], "has no setting 'nope'"), (["mh.chains=3"], "the sampler is smc"),
                        (["smc.islands=x"], "whole number"), (["islands=3"], "SAMPLER.FIELD=VALUE"),
                        (["smc.islands=0"], ">= 1")):
        with pytest.raises(ConfigError, match=needle):
            apply_settings(SMCConfig(), bad)
    from mitsuba_p3.images import write_png

    write_png(tmp_path / "image.png", np.full((12, 16, 3), 0.5))
    done = run("infer", tmp_path / "image.png", "--model", tmp_path, "-o", tmp_path / "out", "--set", "smc.nope=1")
    assert done.returncode != 0 and len(done.stderr.strip().splitlines()) == 1 and "'nope'" in done.stderr
    assert not (tmp_path / "out").exists()


def test_progress_goes_to_stderr_with_plain_lines_in_a_log(capsys):
    """Written to a file, a progress bar keeps stdout clean (commands print JSON there) and stderr
    holds only plain lines: one per phase's end and, between, at most one per ``log_every`` (so an
    error stays the one line after them)."""
    from mitsuba_p3.cli.app import phase_progress_bar, progress_bar

    bar, track = phase_progress_bar("reproduce")
    with bar:
        for phase in ("fsclvr: fit", "fsclvr: posteriors p3"):
            for done in range(1, 5):
                track(phase, done, 4)
    bar, update = progress_bar("train", log_every=0.0)
    with bar:
        for done in range(1, 4):
            update(done, 3)
    out, err = capsys.readouterr()
    assert out == ""
    lines = err.splitlines()                                  # nothing but the plain lines: no bar frames
    assert [line.split(" after ")[0] for line in lines] == [
        "fsclvr: fit: 4/4", "fsclvr: posteriors p3: 4/4", "train: 1/3", "train: 2/3", "train: 3/3"]
    assert "left" not in lines[2] and "left" in lines[3] and "left" not in lines[4]  # a rate needs two reports


def test_time_left_of_a_resumed_run_counts_only_its_own_work(capsys, monkeypatch):
    """A training resumed at iteration 100 of 200 that then does 10 iterations a minute has 9 minutes
    left, not the 1.6 that counting the first 100 as this run's work would give."""
    import time

    from mitsuba_p3.cli.app import progress_bar

    now = [0.0]
    monkeypatch.setattr(time, "monotonic", lambda: now[0])
    bar, update = progress_bar("train", log_every=0.0)
    with bar:
        for done in (100, 110):
            now[0] += 60.0
            update(done, 200)
    lines = capsys.readouterr().err.splitlines()
    assert lines == ["train: 100/200 after 1.0 min", "train: 110/200 after 2.0 min, about 9.0 min left"]


@pytest.mark.parametrize("command", [["fit", "DATA", "--out", "MODEL", "--stages", ","],
                                     ["baseline", "train", "protonets", "DATA", "--out", "TRAINED", "--iterations", "0"]])
def test_an_empty_count_or_list_is_refused_not_read_as_the_default(tmp_path, command):
    """``fit --stages ','`` named no stage (it said "no model.json"); ``baseline train --iterations 0``
    meant 20000 iterations. Both are refused in one line before any work."""
    from mitsuba_p3.benchmarks.generate import generate

    data = tmp_path / "data"
    generate("fsclvr", data, seed=1, size="small", resolution=(12, 16), spp=1)
    paths = {"DATA": data, "MODEL": tmp_path / "model", "TRAINED": tmp_path / "trained"}
    done = run(*[paths.get(part, part) for part in command])
    lines = done.stderr.strip().splitlines()
    assert done.returncode != 0 and len(lines) == 1 and lines[0].startswith("error:"), done.stderr
    assert not (tmp_path / "trained" / "checkpoint.json").exists()


def test_json_files_hold_no_bare_nan(tmp_path):
    """Every JSON the project writes is strict: a NaN or infinity becomes null."""
    import json

    from mitsuba_p3.files import atomic_json

    path = atomic_json(tmp_path / "r.json", {"a": float("nan"), "b": [np.float32(np.inf), 1.5], "c": np.float64(2.0)})
    assert json.loads(path.read_text(), parse_constant=lambda name: pytest.fail(f"bare {name}")) == {
        "a": None, "b": [None, 1.5], "c": 2.0}
