"""The Python API: its names, its input checks, and one set of defaults with the command line."""
from __future__ import annotations

import inspect

import numpy as np
import pytest

import mitsuba_p3 as p3
from mitsuba_p3.errors import ImageError


def test_the_public_names_are_there_and_only_those():
    assert set(p3.__all__) >= {"load_model", "load_image", "infer_image", "Posterior"}
    for name in p3.__all__:
        assert getattr(p3, name) is not None
    with pytest.raises(AttributeError):
        p3.no_such_name


def test_infer_image_takes_the_defaults_of_mitsuba_p3_infer():
    """Every option the two share has one default; the sampler each builds from them is the same."""
    from mitsuba_p3.cli.app import app
    from mitsuba_p3.cli.pipeline_commands import choose_sampler
    from mitsuba_p3.infer.mcmc import SamplerConfig

    command = next(c for c in app.registered_commands if c.callback.__name__ == "infer")
    cli = {name: param.default.default for name, param in inspect.signature(command.callback).parameters.items()}
    api = {name: param.default for name, param in inspect.signature(p3.infer_image).parameters.items()
           if param.default is not inspect.Parameter.empty and name != "progress"}
    assert api and all(cli[name] == value for name, value in api.items()), (cli, api)
    assert choose_sampler(cli["sampler"], SamplerConfig(seed=cli["seed"]), cli["particles"], cli["noise"],
                          cli["sigma"], cli["bridge"], cli["renderer"]) == p3.sampler_config()


@pytest.mark.parametrize("array, message", [
    (np.zeros((6, 8, 3)), "at least 8x8"),
    (np.array([["a", "b"]]), "real numbers"),
    (np.zeros((0, 0)), "real numbers"),
    (np.zeros((16, 16, 2)), "(H, W, 3)"),
    (np.full((30, 40, 3), 2.0), "[0, 1]"),
    (np.full((30, 40, 3), np.nan), "NaN"),
    (np.zeros((30, 30, 3)), "aspect"),
    (np.zeros((30, 40, 4)), "transparent"),
])
def test_an_array_is_checked_as_a_file_is(array, message):
    with pytest.raises(ImageError, match=None) as info:
        p3.load_image(array)
    assert message in str(info.value) and "\n" not in str(info.value)


def test_an_array_in_range_is_the_inference_resolution():
    image = p3.load_image(np.random.default_rng(0).uniform(size=(240, 320, 3)))
    assert image.shape == (120, 160, 3) and image.dtype == np.float32


def test_the_command_line_says_its_version():
    from typer.testing import CliRunner

    from mitsuba_p3.cli.app import app

    result = CliRunner().invoke(app, ["--version"])
    assert result.exit_code == 0 and result.output.strip() == f"mitsuba-p3 {p3.__version__}"


def test_every_command_writes_where_out_says():
    """One spelling for the output on every command: -o and --out (--output stays an alias where it was)."""
    import typer.main

    from mitsuba_p3.cli.app import app

    def commands(group, prefix=()):
        for name, command in group.commands.items():
            if getattr(command, "commands", None):
                yield from commands(command, prefix + (name,))
            else:
                yield prefix + (name,), command

    writers = 0
    for name, command in commands(typer.main.get_command(app)):
        for param in command.params:
            if {"--out", "--output", "-o"} & set(param.opts):
                writers += 1
                assert {"-o", "--out"} <= set(param.opts), (name, param.opts)
    assert writers >= 10


def test_every_numeric_option_has_a_range_and_the_parser_keeps_it():
    from typer.testing import CliRunner

    from mitsuba_p3.cli import app
    from mitsuba_p3.cli.ranges import RANGES, numeric_options

    options = list(numeric_options(app))
    assert len(options) > 40
    missing = sorted({f"{function.__name__} --{name}" for function, name, _ in options if name not in RANGES})
    assert not missing, missing
    runner = CliRunner()
    for arguments in (["benchmark", "generate", "fsclvr", "--out", "x", "--seed", "-1"],
                      ["benchmark", "generate", "fsclvr", "--out", "x", "--seed", str(2**70)],
                      ["benchmark", "generate", "fsclvr", "--out", "x", "--spp", "0"],
                      ["fit", "x", "--out", "y", "--channels", "-1"]):
        result = runner.invoke(app, arguments)
        assert result.exit_code == 2 and "Invalid value" in result.output, (arguments, result.output)
