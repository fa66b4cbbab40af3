"""The pipeline's commands: fit a model, infer one image's posterior, evaluate a benchmark, reproduce the tables."""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import List, Optional

import typer

from ..api import DEFAULT_LIKELIHOOD, DEFAULT_RENDERER, DEFAULT_SAMPLER
from ..concepts import DistanceConfig
from ..evaluate.config import PRESET
from ..fit.model import DEFAULT_STARTS
from ..fit.scene_opt import SceneOptConfig
from ..infer.likelihood import DEFAULT_NOISE
from ..infer.mcmc import SamplerConfig
from ..infer.smc import GPU_PARTICLES, SMCConfig
from .app import app, parse_resolution, phase_progress_bar, progress_bar, sampler_option
from .settings import CONFIG_HELP, SET_HELP, apply_settings


NOISE_HELP = ("Noise model: fitted (the Gaussian fitted to the model's train residuals, with hard shadows, "
              "at the power 1 / their correlation area), sandwich (the same Gaussian at the composite "
              "likelihood's power along the object's outline), robust (the fitted inlier/outlier mixture), spectral (the correlated Gaussian field fitted to the "
              "train residual windows' power spectrum), fields (smooth shading fields on the hypothesis's own object, "
              "its shadow and the rest of the floor, marginalised: a wrong shade or a change of lighting costs little, "
              "the outline keeps its evidence), scaled (the same fields with the image's own noise scale integrated "
              "out: an image the model renders worse than its train images has its evidence tempered by its own "
              "misfit) or paper (sigma 1, no shadows: the paper's).")
SPREAD_HELP = ("Train images per train class whose posteriors fit the protoprograms' concept spread "
               "(sampled like the test images; 0: the paper's programs, tables in RUN/spread0).")
TAILS_HELP = ("The concept's kernels: Student-t ones whose tails and scale are fitted on train classes "
              " or Gaussian "
              "(--gaussian-concepts; tables in RUN/gaussian-concepts).")
KL_HELP = ("The distance's KL direction: image||class (KL(C_I || C_k), chosen on held-out train classes' 1- and "
           "5-shot episodes) or class||image (the paper's; tables in RUN/kl-class-image).")
SAMPLER_HELP_TEXT = ("auto (smc under a fitted noise model, mh under the paper's), smc (tempered SMC over the "
                     "shape classes, weighed by their evidence) or mh (multi-chain Metropolis-Hastings; the chain "
                     "options apply).")


PARTICLES_HELP = (f"SMC particles per hypothesis (default {SMCConfig.particles}; {GPU_PARTICLES} for the JAX "
                  "tracer on a GPU).")
BRIDGE_HELP = ("NP3 under SMC: start from P3's posterior of the image and temper the neural term in (about "
               "a quarter of P3's cost); --no-bridge tempers all of NP3's likelihood in from the prior.")


def choose_sampler(name: str, mh: SamplerConfig, particles: int | None, noise: str, sigma: float | None,
                   bridge: bool = SMCConfig.bridge, renderer: str = "mitsuba") -> SamplerConfig | SMCConfig:
    """The sampler a command's --sampler names (:func:`mitsuba_p3.api.sampler_config`, the Python API's)."""
    from ..api import sampler_config

    return sampler_config(name, noise, sigma, particles, mh.seed, bridge, renderer, mh)


@app.command()
def fit(
    dataset_dir: Path = typer.Argument(..., help="Benchmark folder (its train split is used)."),
    out: Path = typer.Option(..., "-o", "--out", help="Fitted-model folder to write."),
    stages: str = typer.Option("scene,features,priors,noise,rules",
                               help="Comma-separated stages to (re-)run; rules: the attribute rules that infer "
                                    "uses alone, learnt from the material at train images' true poses (after "
                                    "the others; needs the scene, priors and noise stages)."),
    epochs: int = typer.Option(7, help="Scene optimisation epochs."),
    material_passes: int = typer.Option(5, help="Material-only passes per epoch."),
    global_passes: int = typer.Option(5, help="Global-only passes per epoch."),
    learning_rate: float = typer.Option(0.01, help="Adam learning rate."),
    channels: int = typer.Option(3, help="VGG16 channels to select."),
    shadows: bool = typer.Option(True, "--shadows/--no-shadows", help="Hard shadows while fitting."),
    observation: str = typer.Option("phong", help="Observation model: phong (point lights and a constant ambient "
                                                  "term, the paper's), hemisphere (also a fitted sky and ground "
                                                  "that light and are mirrored by every surface) or microfacet (the "
                                                  "GGX microfacet lobe in place of Phong's highlight)."),
    light_radius: float = typer.Option(0.0, help="Widen every light into a disc of this radius (metres): soft "
                                                 "shadows, in the fit and in every render of the model (0: point "
                                                 "lights, the paper's)."),
    light_falloff: float = typer.Option(0.0, help="Lights whose intensity falls off as (D / distance)^2, D this "
                                                  "reference distance in metres (0.5: about the lights' distance "
                                                  "from the table), in the fit and every render of the model (0: "
                                                  "no falloff, the paper's)."),
    light_colour: str = typer.Option(SceneOptConfig.light_colour,
                                     help="white: achromatic lights, the light's tint left to the fitted colours "
                                          "; free: each light an RGB "
                                          "intensity (the paper's)."),
    seed: str = typer.Option(",".join(map(str, DEFAULT_STARTS)),
                             help="Seeds of the lights' random starts (positions and intensities in the light "
                                  "box), comma-separated: the scene is fitted from each and the model keeps the "
                                  "start whose train residuals the fitted noise model explains best (each start "
                                  "in MODEL/starts/, its figures in model.json); one seed fits one start."),
) -> None:
    """Training stage: scene optimisation, feature selection and priors -> a fitted-model folder."""
    from ..errors import FitError
    from ..fit.model import FittedModel, fit_model
    from ..fit.scene_opt import SceneOptConfig

    try:
        seeds = [int(s) for s in seed.split(",") if s.strip()]
    except ValueError:
        seeds = []
    if not seeds:
        raise FitError(f"--seed must be one integer or several, comma-separated (777,1,2,3), got {seed!r}")
    config = SceneOptConfig(epochs=epochs, material_passes=material_passes, global_passes=global_passes,
                            learning_rate=learning_rate, shadows=shadows, light_radius=light_radius,
                            light_falloff=light_falloff, observation=observation, light_colour=light_colour,
                            seed=seeds[0])
    # one bar named by the stage; written to a file (a background fit's log) it prints plain lines
    bar, track_stage = phase_progress_bar("fit")

    def track(stage: str, done: int, total: int, loss: float) -> None:
        track_stage(stage, done, total)

    chosen = [s.strip() for s in stages.split(",") if s.strip()]
    fit_stages = [s for s in chosen if s != "rules"]
    if not chosen:
        raise FitError("no stage to run: name at least one of scene, features, priors, noise, rules")
    with bar:
        model = (fit_model(dataset_dir, out, fit_stages, scene_config=config, channels=channels, progress=track,
                           seeds=seeds) if fit_stages else FittedModel(out))
        if "rules" in chosen:
            from ..infer.truth_rules import write_truth_rules

            rules = write_truth_rules(out, dataset_dir, progress=lambda done, total: track_stage("rules", done, total))
    summary = {stage: {k: v for k, v in figures.items() if k != "config"}
               for stage, figures in model.info["stages"].items()}
    if "rules" in chosen:
        summary["rules"] = {"file": str(rules)}
    typer.echo(json.dumps({"model": str(out), **summary}, indent=2))


@app.command()
def infer(
    image: Path = typer.Argument(..., help="Observed image (PNG/JPEG, or .npy floats in [0, 1])."),
    model: Path = typer.Option(..., "--model", help="Fitted-model folder (mitsuba-p3 fit)."),
    output: Path = typer.Option(..., "-o", "--out", "--output", help="Folder for the posterior and its figures."),
    chains: int = sampler_option("chains", SamplerConfig),
    steps: int = sampler_option("steps", SamplerConfig),
    burn_in: int = sampler_option("burn_in", SamplerConfig),
    tune_rounds: int = sampler_option("tune_rounds", SamplerConfig),
    tune_steps: int = sampler_option("tune_steps", SamplerConfig),
    sampler: str = typer.Option(DEFAULT_SAMPLER, help=SAMPLER_HELP_TEXT),
    particles: Optional[int] = typer.Option(None, help=PARTICLES_HELP),
    bridge: bool = typer.Option(SMCConfig.bridge, "--bridge/--no-bridge", help=BRIDGE_HELP),
    settings: Optional[List[str]] = typer.Option(None, "--set", help=SET_HELP),
    config_file: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP),
    likelihood: str = typer.Option(DEFAULT_LIKELIHOOD, help="p3 (colour) or np3 (colour + neural)."),
    noise: str = typer.Option(DEFAULT_NOISE, help=NOISE_HELP),
    sigma: Optional[float] = typer.Option(None, help="The paper's likelihood at this sigma (it used 0.35 on its "
                                                     "dark set)."),
    renderer: str = typer.Option(DEFAULT_RENDERER, help="mitsuba (pure_callback) or jax (native tracer)."),
    seed: int = typer.Option(0, help="Sampler seed."),
    material_rule: Optional[Path] = typer.Option(
        None, help="A material-kind rule learnt from train posteriors (RUN/material-rule-p3.json, written by "
                   "mitsuba-p3 evaluate); default: the rule learnt from the fit's materials."),
) -> None:
    """Sample the posterior over an image's object (pose, size, class, material); write it and figures."""
    from ..fit.model import FittedModel
    from ..images import load_observation
    from ..infer.posterior import default_likelihood, sample_posterior
    from ..files import claim_output_folder, folder_lock
    from ..infer.report import read_material_rule, write_report

    observed = load_observation(image)
    config = apply_settings(choose_sampler(sampler, SamplerConfig(
        chains=chains, steps=steps, burn_in=burn_in, tune_rounds=tune_rounds, tune_steps=tune_steps, seed=seed),
        particles, noise, sigma, bridge, renderer), settings, config_file)
    # a reader's lock on the model: a fit writing it now is refused here, and no fit starts meanwhile
    with folder_lock(model, "mitsuba-p3 infer", shared=True):
        fitted = FittedModel(model)
        rules = read_material_rule(fitted, material_rule) if material_rule else None   # refused before sampling
        claim_output_folder(output, "posterior.nc", "mitsuba-p3 infer")
        bar, track = phase_progress_bar("sampling")

        with bar:
            posterior = sample_posterior(fitted, observed, default_likelihood(fitted, likelihood, sigma, noise), config,
                                    renderer=renderer, progress=track, attrs={"image": str(image)})
        written = write_report(posterior, fitted, output, renderer=renderer, rules=rules)
    report = json.loads(Path(written["estimate"]).read_text())
    decided = report["attributes"]
    for warning in report["warnings"]:
        typer.echo(f"warning: {warning}", err=True)
    typer.echo(json.dumps({**written, "attributes": {k: decided[k] for k in ("shape", "material", "size", "colour")},
                           "warnings": report["warnings"]}, indent=2))


@app.command()
def sbc(
    model: Path = typer.Option(..., "--model", help="Fitted-model folder (mitsuba-p3 fit) whose own renders "
                                                    "are simulated."),
    out: Path = typer.Option(Path("out/sbc"), "-o", "--out", help="Report folder: sbc.json, sbc.png, calibration.png and "
                                                          "cache.npz, from which a killed run resumes."),
    images: int = typer.Option(200, help="Simulations (scenes drawn from the model's prior)."),
    draws: int = typer.Option(99, help="Posterior draws ranked against each simulation's truth."),
    particles: Optional[int] = typer.Option(None, help=f"SMC particles per hypothesis (default "
                                                       f"{SMCConfig.particles})."),
    resolution: str = typer.Option("120x160", help="HxW of the simulated images."),
    seed: int = typer.Option(0, help="Seed of the simulations and the sampler."),
    noise: str = typer.Option(DEFAULT_NOISE, help="The likelihood: fitted (the Gaussian at power 1 / correlation "
                                                  "area), sandwich (the pose's power), fields (the shading fields' "
                                                  "form) or scaled (the fields with each image's own noise "
                                                  "scale, drawn from the fitted prior and integrated out)."),
    settings: Optional[List[str]] = typer.Option(None, "--set", help=SET_HELP),
    config_file: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP),
    jobs: int = typer.Option(1, help="Parallel simulation workers (processes that live for the whole run)."),
) -> None:
    """Simulation-based calibration of the SMC sampler (the default, or as --set makes it) on a model's own
    renders: do its posteriors' ranks of the truth come out uniform (position, size, colour), and is its
    shape posterior calibrated?"""
    from ..errors import ConfigError
    from ..evaluate.sbc import calibrate_model
    from ..files import claim_output_folder, folder_lock

    if noise not in ("fitted", "sandwich", "fields", "scaled"):
        raise ConfigError(f"--noise must be fitted, sandwich, fields or scaled, got {noise!r}")
    if images < 2 or draws < 1 or jobs < 1:
        raise ConfigError(f"--images must be at least 2, --draws and --jobs at least 1; got {images}, {draws} "
                          f"and {jobs}")
    height, width = parse_resolution(resolution)
    config = apply_settings(SMCConfig(particles=SMCConfig.particles if particles is None else particles), settings,
                            config_file)
    with folder_lock(model, "mitsuba-p3 sbc", shared=True):
        claim_output_folder(out, ("cache.npz", "sbc.json"), "mitsuba-p3 sbc")
        bar, update = progress_bar("simulations")
        with bar:
            summary = calibrate_model(model, out, images, draws, (height, width), seed, noise,
                                      progress=update, config=config, jobs=jobs)
    shown = {k: v for k, v in summary.items() if k != "rank_counts"}
    shown["class"] = {k: v for k, v in summary["class"].items() if k != "reliability"}
    typer.echo(json.dumps(shown, indent=2))


@app.command()
def evaluate(
    dataset: Path = typer.Argument(..., help="Benchmark folder (mitsuba-p3 benchmark generate)."),
    model: Path = typer.Option(..., "--model", help="Fitted-model folder (mitsuba-p3 fit)."),
    out: Path = typer.Option(..., "-o", "--out", help="Run folder: cached posteriors and tables (resumes)."),
    likelihoods: str = typer.Option("p3,np3", help="Comma-separated: p3, np3."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting."),
    jobs: int = typer.Option(1, help="Parallel posterior workers (processes that live for the whole run)."),
    dask: Optional[str] = typer.Option(None, "--dask", help="Dask scheduler address: run the jobs there."),
    chains: int = sampler_option("chains", SamplerConfig),
    steps: int = sampler_option("steps", SamplerConfig),
    burn_in: int = sampler_option("burn_in", SamplerConfig),
    tune_rounds: int = sampler_option("tune_rounds", SamplerConfig),
    tune_steps: int = sampler_option("tune_steps", SamplerConfig),
    sampler: str = typer.Option("auto", help=SAMPLER_HELP_TEXT),
    particles: Optional[int] = typer.Option(None, help=PARTICLES_HELP),
    bridge: bool = typer.Option(SMCConfig.bridge, "--bridge/--no-bridge", help=BRIDGE_HELP),
    settings: Optional[List[str]] = typer.Option(None, "--set", help=SET_HELP),
    config_file: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP),
    noise: str = typer.Option(DEFAULT_NOISE, help=NOISE_HELP + f" {DEFAULT_NOISE}, chosen on train classes "
                                                  "; paper reproduces the paper's rows."),
    sigma: Optional[float] = typer.Option(None, help="The paper's likelihood at this sigma (it used 0.35 on its "
                                                     "dark set)."),
    distance: str = typer.Option("all", help="Distance terms: 'all' (the paper's) or some joined by '+', e.g. "
                                             "colour+class; another distance reuses the run's posteriors and "
                                             "writes its tables to RUN/distance-TERMS."),
    spread_shots: int = typer.Option(DistanceConfig.spread_shots, help=SPREAD_HELP),
    kl: str = typer.Option(DistanceConfig.direction, "--kl", help=KL_HELP),
    concept_tails: bool = typer.Option(DistanceConfig.tails, "--concept-tails/--gaussian-concepts", help=TAILS_HELP),
    spread_from: Optional[Path] = typer.Option(None, help="For a data set without train classes (ood): the "
                                                          "evaluation run of the model's own benchmark, same "
                                                          "settings, whose concept spread to use."),
    renderer: str = typer.Option("mitsuba", help="mitsuba (pure_callback) or jax (native tracer)."),
    seed: int = typer.Option(0, help="Sampler seed."),
) -> None:
    """Few-shot accuracy, calibration and pose error (ADI) of P3/NP3 on a benchmark's test split."""
    from ..concepts import parse_properties
    from ..evaluate import EvaluationConfig, tables_dir
    from ..evaluate import evaluate as run_evaluation

    chosen = tuple(k.strip() for k in likelihoods.split(",") if k.strip())
    config = EvaluationConfig(likelihoods=chosen, sigma=sigma, noise=noise, renderer=renderer, episodes=episodes,
                              jobs=jobs,
                              dask=dask, distance=DistanceConfig(properties=parse_properties(distance),
                                                                 spread_shots=spread_shots, direction=kl,
                                                                 tails=concept_tails),
                              sampler=apply_settings(choose_sampler(sampler, SamplerConfig(
                                  chains=chains, steps=steps, burn_in=burn_in, tune_rounds=tune_rounds,
                                  tune_steps=tune_steps, seed=seed), particles, noise, sigma, bridge, renderer),
                                  settings, config_file))
    bar, track = phase_progress_bar("posteriors")

    with bar:
        results = run_evaluation(dataset, model, out, config, progress=track, spread_from=spread_from)
    summary = {k: {"accuracy": {s: round(100 * a["mean"], 1) for s, a in r["accuracy"].items()},
                   "mean_adi_m": round(r["adi"]["mean"], 4),
                   "attributes": {a: round(v, 3) for a, v in r["attributes"].items()}} for k, r in results.items()}
    tables = tables_dir(out, config.distance)
    typer.echo("\n".join((tables / name).read_text() for name in ("accuracy.md", "adi.md", "attributes.md")))
    typer.echo(json.dumps({"run": str(out), "tables": str(tables), **summary}, indent=2))


@app.command()
def reproduce(
    data: Path = typer.Option(Path("data"), help="Folder of benchmark folders (data/fsclvr, ...) and data/models; "
                                                 "what is missing is generated and fitted."),
    out: Path = typer.Option(Path("out/reproduction"), "-o", "--out", help="Tables, timing log and one run folder per benchmark "
                                                            "(resumes); results/ holds only the frozen snapshots "
                                                            "the docs cite."),
    benchmarks: str = typer.Option("fsclvr,room,dark,ood", help="Comma-separated benchmarks."),
    likelihoods: str = typer.Option("p3,np3", help="Comma-separated: p3, np3."),
    episodes: int = typer.Option(100, help="Episodes per N-way K-shot setting."),
    jobs: int = typer.Option(len(os.sched_getaffinity(0)), help="Parallel posterior workers (default: one per core)."),
    chains: int = sampler_option("chains", PRESET),
    steps: int = sampler_option("steps", PRESET),
    burn_in: int = sampler_option("burn_in", PRESET),
    tune_rounds: int = sampler_option("tune_rounds", PRESET),
    tune_steps: int = sampler_option("tune_steps", PRESET),
    sampler_name: str = typer.Option("auto", "--sampler", help=SAMPLER_HELP_TEXT.replace(
        "multi-chain Metropolis-Hastings", "the evaluation preset")),
    particles: Optional[int] = typer.Option(None, help=PARTICLES_HELP),
    bridge: bool = typer.Option(SMCConfig.bridge, "--bridge/--no-bridge", help=BRIDGE_HELP),
    settings: Optional[List[str]] = typer.Option(None, "--set", help=SET_HELP),
    config_file: Optional[Path] = typer.Option(None, "--config", help=CONFIG_HELP),
    noise: str = typer.Option(DEFAULT_NOISE, help=NOISE_HELP + " Runs go to runs/V-NOISE (e.g. runs/V-sandwich), "
                                                  "runs/V (paper)."),
    sigma: Optional[float] = typer.Option(None, help="The paper's likelihood at this sigma; runs go to "
                                                     "runs/V-sigmaS."),
    distance: str = typer.Option("all", help="Distance terms: 'all' or e.g. colour+class (tables in "
                                             "runs/V/distance-TERMS; the posteriors are shared)."),
    spread_shots: int = typer.Option(DistanceConfig.spread_shots, help=SPREAD_HELP),
    kl: str = typer.Option(DistanceConfig.direction, "--kl", help=KL_HELP),
    concept_tails: bool = typer.Option(DistanceConfig.tails, "--concept-tails/--gaussian-concepts", help=TAILS_HELP),
    resolution: Optional[str] = typer.Option(None, help="HxW of benchmarks generated here (default: 480x640); "
                                                        "folders already made must match it."),
    observation: str = typer.Option("phong", help="Observation model of the fits made here (as fit --observation; "
                                                  "models go to data/models/V-OBSERVATION unless phong); use another "
                                                  "--out than a Phong reproduction's."),
    light_falloff: float = typer.Option(0.0, help="The lights' falloff distance of the fits made here (as fit "
                                                  "--light-falloff; models go to data/models/V-falloffD unless 0, "
                                                  "the paper's world)."),
    light_colour: str = typer.Option(SceneOptConfig.light_colour,
                                     help="The lights' colour in the fits made here (as fit --light-colour; models "
                                          "go to data/models/V-free for the paper's free lights)."),
    tables_only: bool = typer.Option(False, "--tables-only", help="Only write the tables and figures again from "
                                     "the runs and scored baselines already in OUT (nothing generated or sampled)."),
) -> None:
    """Generate, fit and evaluate every benchmark, then write the paper's accuracy and ADI tables."""
    import time
    from dataclasses import replace

    from ..concepts import parse_properties
    from ..evaluate import EvaluationConfig
    from ..reproduce import ReproduceConfig
    from ..reproduce import reproduce as run_reproduction
    from ..reproduce import write_tables

    if tables_only:
        write_tables(out)
        typer.echo((out / "accuracy.md").read_text() + "\n" + (out / "adi.md").read_text())
        return

    sampler = apply_settings(choose_sampler(sampler_name, replace(PRESET, chains=chains, steps=steps, burn_in=burn_in,
                                                                  tune_rounds=tune_rounds, tune_steps=tune_steps),
                                            particles, noise, sigma, bridge), settings, config_file)
    evaluation = EvaluationConfig(likelihoods=tuple(k.strip() for k in likelihoods.split(",") if k.strip()),
                                  sigma=sigma, noise=noise, sampler=sampler, episodes=episodes, jobs=jobs,
                                  distance=DistanceConfig(properties=parse_properties(distance),
                                                          spread_shots=spread_shots, direction=kl,
                                                          tails=concept_tails))
    height, width = parse_resolution(resolution)
    config = ReproduceConfig(observation=observation, light_falloff=light_falloff, light_colour=light_colour,
                             benchmarks=tuple(b.strip() for b in benchmarks.split(",") if b.strip()),
                             evaluation=evaluation, resolution=(height, width) if height else None)
    start = time.perf_counter()
    bar, track = phase_progress_bar("reproduce")
    with bar:
        minutes = run_reproduction(data, out, config, progress=track)
    typer.echo((out / "accuracy.md").read_text() + "\n" + (out / "adi.md").read_text())
    typer.echo(json.dumps({"out": str(out), "minutes": {k: round(v, 1) for k, v in minutes.items()},
                           "total_minutes": round((time.perf_counter() - start) / 60, 1)}, indent=2))
