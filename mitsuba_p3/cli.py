"""`mitsuba-p3` command line: thin subcommands over the library.

Every project error (:class:`~mitsuba_p3.errors.MitsubaP3Error`) becomes one
line on stderr and exit status 2.
"""
from __future__ import annotations

import json
import sys
from pathlib import Path
from typing import List, Optional

import numpy as np
import typer

from .errors import MitsubaP3Error, SceneError
from .infer.mcmc import SamplerConfig

app = typer.Typer(add_completion=False, no_args_is_help=True,
                  help="Bayesian inverse graphics for few-shot concept learning (Mitsuba 3 + JAX).")


# Options shared by the commands that take a scene and change its object.
SHAPE = typer.Option(None, help="sphere, cube or cylinder.")
COLOUR = typer.Option(None, "--color", "--colour", help="CLEVR colour name or 'r,g,b' in [0,1].")
MATERIAL = typer.Option(None, help="rubber or metal.")
SHIFT = typer.Option(None, help="'x,y' position on the floor (m).")
THETA = typer.Option(None, help="Yaw about z (degrees).")
SCALE = typer.Option(None, help="small, large, one half-extent or 'sx,sy,sz' (m).")
SETS = typer.Option(None, "--set", help="Override any <default> NAME=VALUE.")
SHADOWS = typer.Option(None, "--shadows/--no-shadows", help="Hard shadows (default: as the XML).")


def _resolution(text: str | None) -> tuple[int | None, int | None]:
    if not text:
        return None, None
    try:
        height, width = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise SceneError(f"--resolution must look like HxW (e.g. 120x160), got {text!r}") from None
    if height < 1 or width < 1:
        raise SceneError(f"--resolution must be positive, got {text!r}")
    return height, width


def _overrides(shape, color, material, shift, theta, scale, sets) -> dict[str, str]:
    """Command-line options -> the scene file's <default> overrides."""
    from .scene import MATERIALS, SIZES, colour_rgb, _fmt, _vector
    from .shapes import shape_index

    out: dict[str, str] = {}
    for item in sets or []:
        if "=" not in item:
            raise SceneError(f"--set expects NAME=VALUE, got {item!r}")
        name, value = item.split("=", 1)
        out[name.strip()] = value.strip()
    if shape is not None:
        shape_index(shape)
        out["shape"] = shape
    if color is not None:
        out["colour"] = _fmt(colour_rgb(color))
    if material is not None:
        if material not in MATERIALS:
            raise SceneError(f"unknown material {material!r}; choose one of {', '.join(MATERIALS)}")
        for name, value in zip(("ambient", "diffuse", "specular", "shininess"), MATERIALS[material]):
            out[name] = _fmt(value)
    if shift is not None:
        x, y = _vector(shift, 2, "--shift")
        out["shift_x"], out["shift_y"] = _fmt(x), _fmt(y)
    if theta is not None:
        out["theta_deg"] = _fmt(theta)
    if scale is not None:
        values = [SIZES[scale]] * 3 if scale in SIZES else _vector(scale, 3, "--scale")
        if min(values) <= 0:
            raise SceneError(f"--scale must be positive half-extents, got {scale!r}")
        out["scale"] = _fmt(values)
    return out


@app.command()
def render(
    scene_file: Path = typer.Argument(..., help="Scene XML (e.g. scenes/fsclvr.xml)."),
    output: Path = typer.Option(..., "-o", "--output", help="PNG to write."),
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
    from .images import write_png
    from .render import make_renderer
    from .scene import load_scene

    scene = load_scene(scene_file, _overrides(shape, color, material, shift, theta, scale, sets))
    height, width = _resolution(resolution)
    image = make_renderer(scene, renderer, height=height, width=width, shadows=shadows).render()
    write_png(output, image)
    typer.echo(f"wrote {output} ({image.shape[0]}x{image.shape[1]}, {renderer})")


@app.command()
def crosscheck(
    scene_file: Path = typer.Argument(..., help="Scene XML (e.g. scenes/fsclvr.xml)."),
    output: Path = typer.Option(Path("crosscheck.png"), "-o", "--output",
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
    from .images import write_png
    from .render.crosscheck import crosscheck as run_crosscheck
    from .render.crosscheck import difference_image
    from .scene import load_scene

    scene = load_scene(scene_file, _overrides(shape, color, material, shift, theta, scale, sets))
    height, width = _resolution(resolution)
    figures, mitsuba_image, jax_image = run_crosscheck(scene, height=height, width=width, shadows=shadows)
    write_png(output, difference_image(mitsuba_image, jax_image))
    typer.echo(json.dumps({**{k: round(v, 6) for k, v in figures.items()}, "difference_image": str(output)},
                          indent=2))


@app.command()
def doctor() -> None:
    """Check the rendering backend (libLLVM, Mitsuba variant) and print what it runs on."""
    from .backend import describe

    typer.echo(json.dumps(describe(), indent=2))


benchmark_app = typer.Typer(no_args_is_help=True, help="Make, check and look at benchmark data sets.")
app.add_typer(benchmark_app, name="benchmark")


def progress_bar(description: str):
    """A rich progress bar on stderr; returns (context manager, callback(done, total))."""
    from rich.progress import (BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeElapsedColumn,
                               TimeRemainingColumn)

    bar = Progress(TextColumn("[bold]{task.description}"), BarColumn(), MofNCompleteColumn(),
                   TimeElapsedColumn(), TimeRemainingColumn(), transient=False)
    task = bar.add_task(description, total=None)

    def update(done: int, total: int) -> None:
        bar.update(task, completed=done, total=total)

    return bar, update


def phase_progress_bar(description: str):
    """A progress bar whose callback(phase, done, total) also names the current phase."""
    bar, _ = progress_bar(description)

    def track(phase: str, done: int, total: int) -> None:
        bar.update(bar.task_ids[0], description=phase, completed=done, total=total)

    return bar, track


@benchmark_app.command("generate")
def benchmark_generate(
    variant: str = typer.Argument(..., help="fsclvr, dark, room or ood."),
    out: Path = typer.Option(..., "--out", help="Data-set folder to write (resumes if it exists)."),
    seed: int = typer.Option(0, help="Seed: the same seed gives the same labels and images."),
    size: str = typer.Option("full", help="full (BENCHMARK.md counts) or small (built-in example)."),
    resolution: Optional[str] = typer.Option(None, help="HxW (default: 480x640 full, 120x160 small)."),
    spp: Optional[int] = typer.Option(None, help="Samples per pixel (default: the world XML's; 32 small)."),
) -> None:
    """Render a benchmark with Mitsuba's path tracer (world: scenes/benchmarks/VARIANT.xml)."""
    import time

    from .benchmarks.generate import generate

    height, width = _resolution(resolution)
    bar, update = progress_bar(f"{variant} ({size})")
    start = time.perf_counter()
    counts = {}

    def track(done: int, total: int) -> None:
        counts.setdefault("first", done)
        counts["done"], counts["total"] = done, total
        update(done, total)

    with bar:
        labels = generate(variant, out, seed=seed, size=size,
                          resolution=(height, width) if height else None, spp=spp, progress=track)
    rendered = counts["done"] - counts["first"]
    seconds = time.perf_counter() - start
    per_image = f", {seconds / rendered:.2f} s/image" if rendered else ""
    typer.echo(f"wrote {labels.parent}: {counts['total']} images ({rendered} rendered now, "
               f"{counts['first']} already there) in {seconds:.1f} s{per_image}")


@benchmark_app.command("check")
def benchmark_check(
    folder: Path = typer.Argument(..., help="Data-set folder."),
) -> None:
    """Validate a data-set folder and print a summary (JSON)."""
    from .benchmarks.dataset import load_dataset

    dataset = load_dataset(folder)
    typer.echo(json.dumps({"folder": str(folder), "variant": dataset.variant, "images": len(dataset),
                           "train_classes": len(dataset.classes("train")),
                           "test_classes": len(dataset.classes("test"))}, indent=2))


@benchmark_app.command("show")
def benchmark_show(
    folder: Path = typer.Argument(..., help="Data-set folder."),
    output: Path = typer.Option(Path("sheet.png"), "-o", "--output", help="Contact sheet PNG."),
    resolution: str = typer.Option("240x320", help="HxW of each thumbnail."),
) -> None:
    """Contact sheet: one labelled shot per class."""
    from .benchmarks.dataset import load_dataset
    from .plots import contact_sheet

    dataset = load_dataset(folder, resolution=_resolution(resolution))
    contact_sheet(dataset, output)
    typer.echo(f"wrote {output}")


@app.command()
def fit(
    dataset_dir: Path = typer.Argument(..., help="Benchmark folder (its train split is used)."),
    out: Path = typer.Option(..., "--out", help="Fitted-model folder to write."),
    stages: str = typer.Option("scene,features,priors", help="Comma-separated stages to (re-)run."),
    epochs: int = typer.Option(7, help="Scene optimisation epochs."),
    material_passes: int = typer.Option(5, help="Material-only passes per epoch."),
    global_passes: int = typer.Option(5, help="Global-only passes per epoch."),
    learning_rate: float = typer.Option(0.01, help="Adam learning rate."),
    channels: int = typer.Option(3, help="VGG16 channels to select."),
    shadows: bool = typer.Option(True, "--shadows/--no-shadows", help="Hard shadows while fitting."),
) -> None:
    """Training stage: scene optimisation, feature selection and priors -> a fitted-model folder."""
    from .fit.model import fit_model
    from .fit.scene_opt import SceneOptConfig

    config = SceneOptConfig(epochs=epochs, material_passes=material_passes, global_passes=global_passes,
                            learning_rate=learning_rate, shadows=shadows)
    bar, update = progress_bar("fit")
    tasks = {}

    def track(stage: str, done: int, total: int, loss: float) -> None:
        if stage not in tasks:
            tasks[stage] = bar.add_task(stage, total=total)
        description = f"{stage} (loss {loss:.5f})" if stage == "scene" else stage
        bar.update(tasks[stage], completed=done, total=total, description=description)

    with bar:
        bar.remove_task(bar.task_ids[0])
        model = fit_model(dataset_dir, out, [s.strip() for s in stages.split(",") if s.strip()],
                          scene_config=config, channels=channels, progress=track)
    summary = {stage: {k: v for k, v in figures.items() if k != "config"}
               for stage, figures in model.info["stages"].items()}
    typer.echo(json.dumps({"model": str(out), **summary}, indent=2))


@app.command()
def infer(
    image: Path = typer.Argument(..., help="Observed image (PNG/JPEG, or .npy floats in [0, 1])."),
    model: Path = typer.Option(..., "--model", help="Fitted-model folder (mitsuba-p3 fit)."),
    output: Path = typer.Option(..., "-o", "--output", help="Folder for the posterior and its figures."),
    chains: int = typer.Option(SamplerConfig.chains, help="MH chains, run in one batched render per step."),
    steps: int = typer.Option(SamplerConfig.steps, help="Kept draws per chain."),
    burn_in: int = typer.Option(SamplerConfig.burn_in, help="Burn-in steps after tuning."),
    tune_rounds: int = typer.Option(SamplerConfig.tune_rounds, help="Tuning rounds."),
    tune_steps: int = typer.Option(SamplerConfig.tune_steps, help="Steps per tuning round."),
    likelihood: str = typer.Option("np3", help="p3 (colour) or np3 (colour + neural)."),
    sigma: Optional[float] = typer.Option(None, help="Colour-likelihood sigma (default 1.0; 0.35 for dark)."),
    renderer: str = typer.Option("mitsuba", help="mitsuba (pure_callback) or jax (native tracer)."),
    seed: int = typer.Option(0, help="Sampler seed."),
) -> None:
    """Sample the posterior over an image's object (pose, size, class, material); write it and figures."""
    from .fit.model import FittedModel
    from .images import load_observation
    from .infer.posterior import default_likelihood, infer_image
    from .infer.report import write_report

    fitted = FittedModel(model)
    observed = load_observation(image)
    config = SamplerConfig(chains=chains, steps=steps, burn_in=burn_in, tune_rounds=tune_rounds,
                           tune_steps=tune_steps, seed=seed)
    bar, track = phase_progress_bar("sampling")

    with bar:
        posterior = infer_image(fitted, observed, default_likelihood(fitted, likelihood, sigma), config,
                                renderer=renderer, progress=track, attrs={"image": str(image)})
    written = write_report(posterior, fitted, output, renderer=renderer)
    typer.echo(json.dumps(written, indent=2))


@app.command()
def evaluate(
    dataset: Path = typer.Argument(..., help="Benchmark folder (mitsuba-p3 benchmark generate)."),
    model: Path = typer.Option(..., "--model", help="Fitted-model folder (mitsuba-p3 fit)."),
    out: Path = typer.Option(..., "--out", help="Run folder: cached posteriors and tables (resumes)."),
    likelihoods: str = typer.Option("p3,np3", help="Comma-separated: p3, np3."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting."),
    jobs: int = typer.Option(1, help="Parallel posterior jobs (joblib)."),
    dask: Optional[str] = typer.Option(None, "--dask", help="Dask scheduler address: run the jobs there."),
    chains: int = typer.Option(SamplerConfig.chains, help="MH chains per posterior."),
    steps: int = typer.Option(SamplerConfig.steps, help="Kept draws per chain."),
    burn_in: int = typer.Option(SamplerConfig.burn_in, help="Burn-in steps after tuning."),
    tune_rounds: int = typer.Option(SamplerConfig.tune_rounds, help="Tuning rounds."),
    tune_steps: int = typer.Option(SamplerConfig.tune_steps, help="Steps per tuning round."),
    sigma: Optional[float] = typer.Option(None, help="Colour-likelihood sigma (default: the paper's, "
                                                     "1.0; 0.35 for a dark-fitted model)."),
    distance: str = typer.Option("all", help="Distance terms: 'all' (the paper's) or some joined by '+', e.g. "
                                             "colour+class; another distance reuses the run's posteriors and "
                                             "writes its tables to RUN/distance-TERMS."),
    renderer: str = typer.Option("mitsuba", help="mitsuba (pure_callback) or jax (native tracer)."),
    seed: int = typer.Option(0, help="Sampler seed."),
) -> None:
    """Few-shot accuracy, calibration and pose error (ADI) of P3/NP3 on a benchmark's test split."""
    from .concepts import DistanceConfig, parse_properties
    from .evaluate import EvaluationConfig, tables_dir
    from .evaluate import evaluate as run_evaluation

    chosen = tuple(k.strip() for k in likelihoods.split(",") if k.strip())
    unknown = [k for k in chosen if k not in ("p3", "np3")]
    if unknown or not chosen:
        raise MitsubaP3Error(f"unknown likelihood(s) {unknown or likelihoods!r}; choose from p3, np3")
    if renderer not in ("mitsuba", "jax"):
        raise MitsubaP3Error(f"unknown renderer {renderer!r}; choose mitsuba or jax")
    if sigma is not None and not sigma > 0:
        raise MitsubaP3Error(f"--sigma must be positive; got {sigma}")
    config = EvaluationConfig(likelihoods=chosen, sigma=sigma, renderer=renderer, episodes=episodes, jobs=jobs,
                              dask=dask, distance=DistanceConfig(properties=parse_properties(distance)),
                              sampler=SamplerConfig(chains=chains, steps=steps, burn_in=burn_in,
                                                    tune_rounds=tune_rounds, tune_steps=tune_steps, seed=seed))
    bar, track = phase_progress_bar("posteriors")

    with bar:
        results = run_evaluation(dataset, model, out, config, progress=track)
    summary = {k: {"accuracy": {s: round(100 * a["mean"], 1) for s, a in r["accuracy"].items()},
                   "mean_adi_m": round(r["adi"]["mean"], 4)} for k, r in results.items()}
    tables = tables_dir(out, config.distance)
    typer.echo((tables / "accuracy.md").read_text() + "\n" + (tables / "adi.md").read_text())
    typer.echo(json.dumps({"run": str(out), "tables": str(tables), **summary}, indent=2))


baseline_app = typer.Typer(no_args_is_help=True, help="Few-shot baselines: ProtoNets and MAML (Conv-4).")
app.add_typer(baseline_app, name="baseline")


@baseline_app.command("train")
def baseline_train(
    method: str = typer.Argument(..., help="protonets or maml."),
    dataset: Path = typer.Argument(..., help="Benchmark folder; its train split is used."),
    out: Path = typer.Option(..., "--out", help="Training folder (checkpoint, curve; resumes)."),
    resolution: int = typer.Option(56, help="Square input size: 56 or 84 as in the paper."),
    iterations: Optional[int] = typer.Option(None, help="Meta-iterations (default: protonets 2000, maml 1000)."),
    k_shot: int = typer.Option(1, help="Shots per class in the training tasks."),
    second_order: bool = typer.Option(False, help="MAML: differentiate through the inner loop."),
    seed: int = typer.Option(0),
) -> None:
    """Meta-train a baseline on a benchmark's train classes, with checkpoints and a learning curve."""
    from .baselines.train import DEFAULT_ITERATIONS, TrainConfig, train_baseline

    if resolution not in (56, 84):
        raise MitsubaP3Error("--resolution must be 56 or 84 (the paper's inputs)")
    config = TrainConfig(method=method, resolution=resolution, k_shot=k_shot, second_order=second_order, seed=seed,
                         iterations=iterations or DEFAULT_ITERATIONS.get(method, 1000))
    bar, update = progress_bar(f"{method} {resolution}")
    with bar:
        state = train_baseline(dataset, out, config, progress=update)
    last = state.curve[-100:]
    typer.echo(json.dumps({"out": str(out), "iterations": state.iteration,
                           "recent_loss": round(float(np.mean([c[1] for c in last])), 4),
                           "recent_query_accuracy": round(float(np.mean([c[2] for c in last])), 4),
                           "learning_curve": str(out / "learning_curve.png")}, indent=2))


@baseline_app.command("evaluate")
def baseline_evaluate(
    trained: Path = typer.Argument(..., help="Training folder (mitsuba-p3 baseline train)."),
    dataset: Path = typer.Argument(..., help="Benchmark folder; its test episodes are used."),
    out: Path = typer.Option(..., "--out", help="Evaluation run folder (results go to baselines/)."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting (same as evaluate)."),
) -> None:
    """Accuracy on the same test episodes as P3/NP3; the evaluation tables pick it up."""
    from .baselines.train import evaluate_baseline

    bar, update = progress_bar("episodes")
    with bar:
        result = evaluate_baseline(trained, dataset, out, episodes, progress=update)
    typer.echo(json.dumps({result["model"]: {k: round(100 * v["mean"], 1) for k, v in result["accuracy"].items()}},
                          indent=2))


def main() -> None:
    try:
        app()
    except MitsubaP3Error as exc:
        typer.echo(f"error: {exc}", err=True)
        sys.exit(2)


if __name__ == "__main__":
    main()
