"""Scene commands: render a scene XML, cross-check the two renderers, check the backend."""
from __future__ import annotations

import json
from pathlib import Path
from typing import List, Optional

import typer

from .app import COLOUR, MATERIAL, SCALE, SETS, SHADOWS, SHAPE, SHIFT, THETA, app, parse_resolution


@app.command()
def render(
    scene_file: Path = typer.Argument(..., help="Scene XML (e.g. scenes/fsclvr.xml)."),
    output: Path = typer.Option(..., "-o", "--out", "--output", help="Image to write (.png or .jpg)."),
    shape: Optional[str] = SHAPE,
    color: Optional[str] = COLOUR,
    material: Optional[str] = MATERIAL,
    shift: Optional[str] = SHIFT,
    theta: Optional[float] = THETA,
    scale: Optional[str] = SCALE,
    sets: Optional[List[str]] = SETS,
    shadows: Optional[bool] = SHADOWS,
    resolution: Optional[str] = typer.Option(None, help="HxW (default: the XML's film)."),
    renderer: str = typer.Option("mitsuba", help="Renderer: mitsuba or jax."),
) -> None:
    """Render a scene XML to a PNG, optionally changing the object."""
    from ..images import check_image_output, write_image
    from ..render import make_renderer
    from ..scene import load_scene, object_overrides

    check_image_output(output)
    scene = load_scene(scene_file, object_overrides(shape, color, material, shift, theta, scale, sets))
    height, width = parse_resolution(resolution)
    image = make_renderer(scene, renderer, height=height, width=width, shadows=shadows).render()
    write_image(output, image)
    typer.echo(f"wrote {output} ({image.shape[0]}x{image.shape[1]}, {renderer})")


@app.command()
def crosscheck(
    scene_file: Path = typer.Argument(..., help="Scene XML (e.g. scenes/fsclvr.xml)."),
    output: Path = typer.Option(Path("crosscheck.png"), "-o", "--out", "--output",
                                help="Difference image: Mitsuba | JAX | 10x |difference|."),
    shape: Optional[str] = SHAPE,
    color: Optional[str] = COLOUR,
    material: Optional[str] = MATERIAL,
    shift: Optional[str] = SHIFT,
    theta: Optional[float] = THETA,
    scale: Optional[str] = SCALE,
    sets: Optional[List[str]] = SETS,
    shadows: Optional[bool] = SHADOWS,
    resolution: Optional[str] = typer.Option("120x160", help="HxW."),
) -> None:
    """Render a scene with Mitsuba and with the JAX tracer; print agreement figures (JSON)."""
    from ..images import check_image_output, write_image
    from ..render.crosscheck import crosscheck as run_crosscheck
    from ..render.crosscheck import difference_image
    from ..scene import load_scene, object_overrides

    check_image_output(output)
    scene = load_scene(scene_file, object_overrides(shape, color, material, shift, theta, scale, sets))
    height, width = parse_resolution(resolution)
    figures, mitsuba_image, jax_image = run_crosscheck(scene, height=height, width=width, shadows=shadows)
    write_image(output, difference_image(mitsuba_image, jax_image))
    typer.echo(json.dumps({**{k: round(v, 6) for k, v in figures.items()}, "difference_image": str(output)},
                          indent=2))


@app.command()
def doctor() -> None:
    """Check the rendering backend (libLLVM, Mitsuba variant) and print what it runs on, and the choices that
    follow the device: the JAX tracer's batching and where a plain SMC step runs."""
    from ..backend import describe
    from ..infer.device_step import step_for
    from ..render.jax_tracer import batching_for

    typer.echo(json.dumps({**describe(), "jax_batching": batching_for(), "smc_step": step_for()}, indent=2))
