"""Benchmark commands: generate, check and look at data sets."""
from __future__ import annotations

import json
from pathlib import Path
from typing import Optional

import typer

from .app import benchmark_app, parse_resolution, progress_bar


@benchmark_app.command("generate")
def benchmark_generate(
    variant: str = typer.Argument(..., help="fsclvr, dark, room, ood or studio."),
    out: Path = typer.Option(..., "-o", "--out", help="Data-set folder to write (resumes if it exists)."),
    seed: int = typer.Option(0, help="Seed: the same seed gives the same labels and images."),
    size: str = typer.Option("full", help="full (BENCHMARK.md counts) or small (built-in example)."),
    resolution: Optional[str] = typer.Option(None, help="HxW (default: 480x640 full, 120x160 small)."),
    spp: Optional[int] = typer.Option(None, help="Samples per pixel (default: the world XML's; 32 small)."),
    world: Optional[Path] = typer.Option(None, help="A world to render instead of the variant's (an "
                                         "edited copy of scenes/benchmarks/VARIANT.xml, or of "
                                         "VARIANT.cycles.json with --renderer cycles); the variant keeps "
                                         "choosing classes and poses."),
    renderer: str = typer.Option("mitsuba", help="mitsuba (the project's worlds) or cycles (Blender Cycles "
                                 "with CLEVR's own assets, as the paper's benchmarks were made; needs "
                                 "pip install 'mitsuba-p3[blender]' and --assets)."),
    assets: Optional[Path] = typer.Option(None, help="--renderer cycles: the folder of CLEVR's asset files "
                                          "(base_scene.blend, shapes/, materials/)."),
) -> None:
    """Render a benchmark with Mitsuba's path tracer (world: scenes/benchmarks/VARIANT.xml, or --world), or
    with Blender Cycles from CLEVR's assets (--renderer cycles; default size 240x320, CLEVR's)."""
    import time

    from ..benchmarks.generate import generate

    height, width = parse_resolution(resolution)
    bar, update = progress_bar(f"{variant} ({size})")
    start = time.perf_counter()
    counts = {}

    def track(done: int, total: int) -> None:
        counts.setdefault("first", done)
        counts["done"], counts["total"] = done, total
        update(done, total)

    with bar:
        labels = generate(variant, out, seed=seed, size=size,
                          resolution=(height, width) if height else None, spp=spp, progress=track,
                          world=world, renderer=renderer, assets=assets)
    rendered = counts["done"] - counts["first"]
    seconds = time.perf_counter() - start
    per_image = f", {seconds / rendered:.2f} s/image" if rendered else ""
    typer.echo(f"wrote {labels.parent}: {counts['total']} images ({rendered} rendered now, "
               f"{counts['first']} already there) in {seconds:.1f} s{per_image}")


@benchmark_app.command("check")
def benchmark_check(
    folder: Path = typer.Argument(..., help="Data-set folder."),
) -> None:
    """Validate a data-set folder and print a summary (JSON): the labels (types, ranges, pose consistency,
    duplicate files, train/test leaks), and every image and mesh read by the loaders fit and evaluate use."""
    from ..benchmarks.dataset import check_contents, load_dataset
    from ..concepts import DistanceConfig
    from ..evaluate.metrics import setting_name, test_settings

    dataset = load_dataset(folder)
    check_contents(dataset)
    train, test = dataset.classes("train"), dataset.classes("test")
    settings = [setting_name(n, k) for n, k in test_settings(dataset)]
    if not DistanceConfig.spread_shots:
        spread = "off"
    elif any(len(dataset.shots_of(c)) >= 2 for c in train):
        spread = "from this data set's train classes"
    else:
        spread = "needs --spread-from RUN (no train class has 2 images) or --spread-shots 0"
    typer.echo(json.dumps({
        "folder": str(folder), "variant": dataset.variant, "images": len(dataset), "train_classes": len(train),
        "test_classes": len(test),
        "fit": "ready" if train else "no train images: fit a model on another data set and pass --model",
        "evaluate": settings or "no few-shot setting: it needs 5 test classes with 2 or more images each",
        "concept_spread": spread,
    }, indent=2))


@benchmark_app.command("show")
def benchmark_show(
    folder: Path = typer.Argument(..., help="Data-set folder."),
    output: Path = typer.Option(Path("sheet.png"), "-o", "--out", "--output", help="Contact sheet (.png or .jpg)."),
    resolution: str = typer.Option("240x320", help="HxW of each thumbnail."),
) -> None:
    """Contact sheet: one labelled shot per class."""
    from ..benchmarks.dataset import load_dataset
    from ..images import check_image_output
    from ..plots import contact_sheet

    check_image_output(output)
    dataset = load_dataset(folder, resolution=parse_resolution(resolution))
    contact_sheet(dataset, output)
    typer.echo(f"wrote {output}")
