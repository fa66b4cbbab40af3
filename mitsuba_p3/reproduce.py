"""The pipeline in one call: generate -> fit -> evaluate -> the paper's tables, resumable.

For fsclvr, dark and room: generate the benchmark (only the images missing),
fit a model to it (if missing) and evaluate P3 and NP3 on its test split; ood is
evaluated with the fsclvr model, as in the paper, and with the concept spread of
the fsclvr run (it has no train classes of its own). Every step resumes: benchmarks,
fits and per-image posteriors already on disk are reused. Writes, in ``out``:

- ``accuracy.md`` / ``accuracy.csv``: the paper's layout (rows: models; columns:
  benchmarks; cells: 5-way 1-shot / 5-way 5-shot / 10-way 1-shot / 10-way 5-shot
  accuracy in %), this project's numbers beside the paper's;
- ``adi.md`` / ``adi.csv``: mean ADI (metres) per benchmark beside the paper's;
- ``figures/accuracy.png``: the accuracy table as bars with 95% intervals, the paper's P3 as ticks;
  ``figures/attributes.png``: how often each row's posteriors name shape, material, size and colour right;
  ``figures/reliability-V.png``: per benchmark, accuracy against confidence of its rows' episodes;
  ``figures/posterior-V.png``: per benchmark, one test image's posterior (the observation, the point
  estimate's render and renders of six draws), sampled again with the run's settings
  (:func:`posterior_figure`; its posterior and the other figures of ``mitsuba-p3 infer`` in
  ``runs/V/example``);
- ``runs/V``: one evaluation run folder per benchmark, with its own tables and figures;
- ``timing.json``: the minutes of every benchmark of every invocation (generating and fitting, evaluating,
  the posterior figure and tables: together the invocation's wall time).

The default likelihood is each model's fitted Gaussian noise at the power 1 / correlation area
(:data:`~mitsuba_p3.infer.likelihood.DEFAULT_NOISE`), sampled by SMC (its runs go to
``runs/V-fitted``; another of the model's noise models to ``runs/V-NOISE``); the paper's (``noise="paper"``, sigma 1, MH at the evaluation preset)
to ``runs/V``, with another sigma to ``runs/V-sigmaS``; each gets its own rows. Another
distance scores the same posteriors and its tables go to
``runs/V/distance-TERMS`` (rows such as "NP3 (colour+class)"). Baselines
evaluated into ``runs/V`` (``mitsuba-p3 baseline evaluate TRAINED data/V --out
OUT/runs/V``) join the accuracy table. :func:`write_tables` (``mitsuba-p3 reproduce --tables-only``)
writes the tables and figures again from the run folders alone, sampling nothing: after a baseline
is scored, or in a folder of results copied without its posteriors.

``mitsuba-p3 reproduce`` and ``scripts/reproduce_tables.py`` call :func:`reproduce`.
"""
from __future__ import annotations

import csv
import json
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

from .benchmarks.protocol import VARIANTS
from .errors import ConfigError, EvaluationError
from .evaluate import SETTINGS, EvaluationConfig, evaluate, load_baselines, markdown_table, setting_name
from .evaluate.run import sample_spread
from .files import atomic_json, atomic_open, atomic_write
from .fit.scene_opt import OBSERVATIONS, SceneOptConfig
from .infer.likelihood import DEFAULT_NOISE, NOISES

PAPER_ACCURACY = {  # shared/PAPER_NOTES.md: 5w1s / 5w5s / 10w1s / 10w5s (their data sets)
    "MAML 56": {"fsclvr": "77.0/87.5/62.8/69.8", "room": "77.9/79.2/47.2/61.5", "dark": "79.6/86.2/60.4/62.8",
                "ood": "47.2/32.7/36.6/39.2"},
    "ProtoNets 56": {"fsclvr": "60.5/85.5/51.2/79.7", "room": "66.7/83.0/54.7/72.2",
                     "dark": "65.3/86.7/52.9/79.3", "ood": "49.8/67.3/39.1/57.4"},
    "P3": {"fsclvr": "96.0/99.0/92.6/97.5", "room": "91.7/97.0/86.0/93.6", "dark": "96.9/98.0/93.9/96.6",
           "ood": "66.4/67.8/60.3/57.3"},
    "NP3": {"fsclvr": "97.2/98.9/94.5/97.5", "room": "94.4/99.0/90.5/97.5", "dark": "97.3/98.5/94.9/97.3",
            "ood": "67.4/71.3/62.1/61.4"},
}
PAPER_ADI = {"fsclvr": (0.0152, 0.0133), "room": (0.0185, 0.0180), "dark": (0.0571, 0.0480),
             "ood": (0.0360, 0.0353)}
COLUMNS = ("fsclvr", "room", "dark", "ood")
TITLES = {"fsclvr": "FS-CLVR", "room": "ROOM", "dark": "DARK", "ood": "OOD"}
ATTRIBUTES = {"shape_accuracy": "shape", "shape_accuracy_large": "shape (large)", "material_accuracy": "material",
              "size_accuracy": "size", "colour_accuracy": "colour"}   # results' attribute keys -> figure labels


@dataclass(frozen=True)
class ReproduceConfig:
    """Which benchmarks, and how each is evaluated (by default: the model's fitted noise model and SMC;
    the paper's rows need ``EvaluationConfig(noise="paper", sampler=PRESET)``)."""

    benchmarks: tuple = COLUMNS
    evaluation: EvaluationConfig = field(default_factory=EvaluationConfig)
    resolution: tuple | None = None    # (H, W) of generated benchmarks; None: the benchmark's default
    observation: str = "phong"         # the observation model of the fits made here (fit --observation)
    light_falloff: float = 0.0         # the lights' falloff distance of the fits made here (fit --light-falloff)
    light_colour: str = SceneOptConfig.light_colour   # the lights' colour in the fits made here (fit --light-colour)

    def __post_init__(self):
        if self.observation not in OBSERVATIONS:
            raise ConfigError(f"unknown observation model {self.observation!r}; choose {' or '.join(OBSERVATIONS)}")
        # refuses a bad distance or light colour before anything is generated
        SceneOptConfig(light_falloff=self.light_falloff, light_colour=self.light_colour)
        object.__setattr__(self, "light_falloff", float(self.light_falloff))
        object.__setattr__(self, "benchmarks", tuple(self.benchmarks))
        if self.resolution is not None:
            object.__setattr__(self, "resolution", tuple(int(v) for v in self.resolution))
            if len(self.resolution) != 2 or min(self.resolution) < 8:
                raise ConfigError(f"resolution must be (height, width), each at least 8; got {self.resolution}")
        unknown = [b for b in self.benchmarks if b not in VARIANTS]
        if unknown or not self.benchmarks or len(set(self.benchmarks)) != len(self.benchmarks):
            raise ConfigError(f"benchmarks must be distinct names from {', '.join(VARIANTS)}; "
                              f"got {', '.join(self.benchmarks) or 'none'}")


def prepare(data: Path, variant: str, progress: Callable[[str, int, int], None] | None = None,
            resolution: tuple[int, int] | None = None, observation: str = "phong",
            light_falloff: float = 0.0, light_colour: str = SceneOptConfig.light_colour) -> tuple[Path, Path]:
    """The benchmark folder and the model folder evaluation uses (made when missing; generated at
    ``resolution``, (H, W), or the benchmark's default; fitted with the ``observation`` model and the lights'
    ``light_falloff`` and ``light_colour``, in the folder :func:`model_name` names)."""
    from .benchmarks.generate import generate
    from .fit.model import DEFAULT_STARTS, FittedModel, fit_model

    folder = data / variant
    generate(variant, folder, resolution=resolution,
             progress=(lambda d, t: progress(f"{variant}: generate", d, t)) if progress else None)
    source = fitted_on(variant)
    model = data / "models" / model_name(source, observation, light_falloff, light_colour)
    if not (model / "model.json").exists():
        if source != variant:
            generate(source, data / source, resolution=resolution)
        fit_model(data / source, model, scene_config=SceneOptConfig(observation=observation,
                                                                    light_falloff=light_falloff,
                                                                    light_colour=light_colour),
                  seeds=DEFAULT_STARTS,
                  progress=(lambda stage, d, t, _: progress(f"{source}: fit {stage}", d, t)) if progress else None)
        return folder, model
    # a folder already there (a user's own fit, or an earlier call's) must be the world asked for
    existing = FittedModel(model)
    fitted = float(existing.globals.get("light_falloff", 0.0))
    if abs(fitted - light_falloff) > 1e-6:
        raise ConfigError(f"{model} was fitted with light falloff {fitted:g}, not the {light_falloff:g} asked for; "
                          f"move it away or ask for {fitted:g}")
    # a folder fitted before the option existed has the paper's free lights
    colour = existing.info["stages"].get("scene", {}).get("config", {}).get("light_colour", "free")
    if colour != light_colour:
        raise ConfigError(f"{model} was fitted with {colour} lights, not the {light_colour} asked for; "
                          f"move it away or ask for {colour}")
    return folder, model


def model_name(source: str, observation: str = "phong", light_falloff: float = 0.0,
               light_colour: str = SceneOptConfig.light_colour) -> str:
    """The model folder's name under ``data/models``: the benchmark's own for the default world (Phong, no
    falloff, white lights), else with the observation model, ``falloffD`` and ``free`` (the paper's free
    lights) appended (``fsclvr-microfacet-falloff0.5-free``)."""
    name = source if observation == "phong" else f"{source}-{observation}"
    name = name if light_falloff == 0 else f"{name}-falloff{light_falloff:g}"
    return name if light_colour == SceneOptConfig.light_colour else f"{name}-{light_colour}"


def fitted_on(variant: str) -> str:
    """The benchmark whose train classes a benchmark's model (and frozen baseline) is fitted on: its own, or
    fsclvr's for ood, which has none."""
    return "fsclvr" if variant == "ood" else variant


def frozen_baselines(folder: Path, train_folder: Path, run_dir: Path, episodes: int, track=None) -> None:
    """Score the frozen-feature baselines (:mod:`mitsuba_p3.baselines.frozen`: no training, about a minute)
    on the run's episodes, once (kept when their files are there); skipped for a benchmark with too few
    train classes to choose their layer on."""
    from .baselines.frozen import METHODS, MIN_TRAIN_CLASSES, score_benchmark
    from .benchmarks.dataset import load_dataset

    if all((run_dir / "baselines" / f"frozen-{m}.json").is_file() for m in METHODS):
        return
    if len(load_dataset(train_folder).classes("train")) < MIN_TRAIN_CLASSES:
        return
    score_benchmark(folder, run_dir, None if train_folder == folder else train_folder, episodes,
                    progress=(lambda d, t: track("frozen baselines", d, t)) if track else None)


def machine() -> dict:
    """Where a timing was made: the Mitsuba variant, CPU cores, the GPU (if any) and JAX's backend."""
    from .backend import describe

    keys = ("variant", "cpu_cores", "cpu", "threads", "gpu", "gpu_driver", "jax_backend")
    return {k: v for k, v in describe().items() if k in keys}


def reproduce(data: str | Path, out: str | Path, config: ReproduceConfig | None = None,
              progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Generate, fit and evaluate every benchmark of ``config``, then write the paper's tables in ``out``;
    returns {benchmark: minutes}. A killed call resumes where it stopped."""
    config = config or ReproduceConfig()
    data, out = Path(data), Path(out)
    evaluation = config.evaluation
    from .files import refuse_protected_folder

    refuse_protected_folder(out, "mitsuba-p3 reproduce")
    out.mkdir(parents=True, exist_ok=True)
    timing_log = out / "timing.json"
    started = time.strftime("%Y-%m-%dT%H:%M:%S")
    minutes = {}
    for variant in config.benchmarks:
        start = time.perf_counter()
        folder, model = prepare(data, variant, progress, config.resolution, config.observation,
                                config.light_falloff, config.light_colour)
        prepared = (time.perf_counter() - start) / 60
        start = time.perf_counter()
        noise = evaluation.noise if evaluation.noise != "paper" and evaluation.sigma is None else evaluation.sigma
        track = (lambda phase, d, t: progress(f"{variant}: {phase}", d, t)) if progress else None
        spread_from = None
        if variant == "ood" and evaluation.distance.spread_shots:
            # ood has no train classes: its programs take the concept spread of the fsclvr run
            spread_from = out / "runs" / run_name("fsclvr", noise)
            sample_spread(data / "fsclvr", model, spread_from, evaluation, track)
        run_dir = out / "runs" / run_name(variant, noise)
        evaluate(folder, model, run_dir, evaluation, progress=track, spread_from=spread_from)
        frozen_baselines(folder, data / fitted_on(variant), run_dir, evaluation.episodes, track)
        minutes[variant] = (time.perf_counter() - start) / 60
        start = time.perf_counter()
        posterior_figure(folder, model, run_dir, evaluation, out / "figures" / posterior_figure_name(variant, noise))
        # the tables cover every benchmark and sigma evaluated so far, this run's included
        write_paper_tables(out, collect(out))
        reported = (time.perf_counter() - start) / 60
        # wall-clock minutes per invocation, appended: a resumed reproduction adds its parts up
        log = json.loads(timing_log.read_text()) if timing_log.is_file() else []
        log.append({"invocation": started, "benchmark": variant, "likelihoods": list(evaluation.likelihoods),
                    "sigma": evaluation.sigma, "noise": evaluation.noise, "distance": "+".join(evaluation.distance.properties),
                    "jobs": evaluation.jobs, "episodes": evaluation.episodes, "minutes": round(minutes[variant], 2),
                    "generate_and_fit_minutes": round(prepared, 2),
                    "figure_and_tables_minutes": round(reported, 2), "sampler": asdict(evaluation.sampler),
                    "machine": machine()})
        atomic_json(timing_log, log)
    return minutes


def write_tables(out: str | Path) -> None:
    """The paper's tables and figures from the evaluated runs and scored baselines already in
    ``out/runs`` (:func:`collect`), generating, fitting and sampling nothing."""
    out = Path(out)
    found = collect(out)
    if not found and not any(load_baselines(out / "runs" / c) for c in COLUMNS):
        raise EvaluationError(f"{out} holds no evaluated run (runs/V/results.json) and no scored baseline "
                              f"(runs/V/baselines/): nothing to tabulate")
    write_paper_tables(out, found)


def cells(result: dict) -> str:
    names = [setting_name(n, k) for n, k in SETTINGS]
    return "/".join(f"{100 * result['accuracy'][n]['mean']:.1f}" if n in result["accuracy"] else "-" for n in names)


# the model's noise models, each with its own run folder and table rows (the paper's is the plain name)
FITTED_NOISES = tuple(n for n in NOISES if n != "paper")


def run_name(variant: str, sigma: float | str | None) -> str:
    """The run folder of a benchmark: ``V`` with the paper's likelihood (``sigma`` None), ``V-fitted`` /
    ``V-robust`` with the model's noise model of that name, ``V-sigmaS`` with the paper's form at sigma S."""
    if sigma is None:
        return variant
    return f"{variant}-{sigma}" if sigma in FITTED_NOISES else f"{variant}-sigma{sigma:g}"


def parse_run_name(name: str) -> tuple[str, float | str | None] | None:
    """(benchmark, sigma) of a run folder name (see :func:`run_name`), or None for a folder it did not make."""
    variant, _, noise = name.rpartition("-")
    if noise in FITTED_NOISES and variant in COLUMNS:
        return variant, noise
    variant, _, rest = name.partition("-sigma")
    if variant not in COLUMNS:
        return None
    try:
        return variant, (float(rest) if rest else None)
    except ValueError:
        return None


def _describe(part: str) -> str:
    if part == "spread0":
        return "no concept spread"
    if part in ("gaussian-concepts", "concept-tails"):
        return "Gaussian concept kernels" if part == "gaussian-concepts" else "concept kernels with fitted tails"
    if part.startswith("kl-"):
        first, second = part.removeprefix("kl-").split("-", 1)
        return f"KL({first} || {second})"
    return f"spread of {part.removeprefix('spread')} train images" if part.startswith("spread") else part


def label(likelihood: str, sigma: float | str | None, distance: str | None = None) -> str:
    """A table row's name: ``P3``, ``P3 (fitted noise)``, ``P3 (sigma 0.3)``, ``NP3 (colour+class)``, ..."""
    noise = [] if sigma is None else [f"{sigma} noise"] if sigma in FITTED_NOISES else [f"sigma {sigma:g}"]
    # a tables folder's name: distance terms and/or the concept spread (spread0: the paper's programs)
    parts = (distance.replace("-spread", "\0spread").replace("-kl-", "\0kl-").replace("-gaussian-concepts", "\0gaussian-concepts")
             .replace("-concept-tails", "\0concept-tails").split("\0") if distance else [])
    notes = noise + [_describe(part) for part in parts]
    return likelihood.upper() + (f" ({', '.join(notes)})" if notes else "")


def _noise_order(sigma) -> tuple:
    if sigma in FITTED_NOISES:
        return (1, float(FITTED_NOISES.index(sigma)))
    return (0, 0.0) if sigma is None else (2, float(sigma))


def example_shot(dataset):
    """The test image a benchmark's posterior figure shows: a seeded choice, so every run shows the same."""
    import numpy as np

    test = dataset.split("test")
    return test[int(np.random.default_rng(0).integers(len(test)))]


def posterior_figure_name(variant: str, sigma: float | str | None) -> str:
    """``posterior-V.png`` for the headline run (the default noise model), ``posterior-V-paper.png``
    for the paper's likelihood and ``posterior-RUN.png`` for any other run of the benchmark, so that
    a run with other settings does not overwrite the headline's figure."""
    name = run_name(variant, sigma)
    if name == run_name(variant, DEFAULT_NOISE):
        return f"posterior-{variant}.png"
    return f"posterior-{variant}-paper.png" if name == variant else f"posterior-{name}.png"


def posterior_figure(folder: Path, model: Path, run_dir: Path, evaluation: EvaluationConfig, figure: Path) -> Path:
    """One test image's posterior, sampled with the run's first likelihood, noise and sampler, written
    as ``mitsuba-p3 infer`` writes it to ``run_dir/example``, and its renders copied to ``figure``.
    Kept once made (a resumed reproduction does not sample it again)."""
    import shutil

    from .benchmarks.dataset import load_dataset
    from .fit.model import FittedModel
    from .infer.posterior import default_likelihood, sample_posterior
    from .infer.report import write_report

    example = run_dir / "example"
    if not (example / "posterior.png").is_file():
        dataset = load_dataset(folder)
        shot = example_shot(dataset)
        fitted = FittedModel(model)
        likelihood = default_likelihood(fitted, evaluation.likelihoods[0], evaluation.sigma, evaluation.noise)
        posterior = sample_posterior(fitted, dataset.image(shot), likelihood, evaluation.sampler,
                                renderer=evaluation.renderer,
                                attrs={"image": str(shot.file), "class": shot.class_name})
        write_report(posterior, fitted, example, renderer=evaluation.renderer,
                     truth={"shift": shot.position[:2].tolist()})
    figure.parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(example / "posterior.png", figure)
    return figure


def run_identity(run: Path) -> tuple[str, float | str | None] | None:
    """(benchmark, sigma) of a run folder, as :func:`run_name` names it, from what its ``run.json`` says
    it is (the benchmark; the noise model or the paper's sigma), not from the folder's name; a record
    from before it named the benchmark takes it from the data set's labels, then from the name. A folder
    without a record (results copied without it) is read by its name; None: not a run."""
    record_path = run / "run.json"
    if not record_path.is_file():
        return parse_run_name(run.name)
    try:
        record = json.loads(record_path.read_text())
    except ValueError:
        return None
    if not isinstance(record, dict) or record.get("format") != "mitsuba-p3-evaluation":
        return None
    benchmark = record.get("benchmark")
    if benchmark is None:
        labels = Path(str(record.get("dataset", ""))) / "labels.json"
        try:
            benchmark = json.loads(labels.read_text()).get("variant")
        except (OSError, ValueError):
            benchmark = (parse_run_name(run.name) or (None,))[0]
    if benchmark not in COLUMNS:
        return None
    sigma, noise = record.get("sigma"), record.get("noise", "paper")
    return benchmark, sigma if sigma is not None else (None if noise == "paper" else noise)


def collect(out: Path) -> dict:
    """Every evaluated run under ``out/runs``: {(benchmark, sigma, distance): {likelihood: result}}, where
    distance is None for the default distance and e.g. ``colour+class`` for tables in ``runs/V/distance-colour+class``
    (``spread0`` for the paper's distance over programs without a concept spread, ``kl-class-image`` for the
    paper's KL direction, ``gaussian-concepts`` for the concept's Gaussian kernels)."""
    found = {}
    for run in sorted((out / "runs").glob("*/")):
        key = run_identity(run)
        if key is None:
            continue
        tables = [run / "results.json"] + [path for folder in ("distance-*", "spread*", "kl-*", "gaussian-concepts",
                                                               "concept-tails")
                                           for path in sorted(run.glob(f"{folder}/results.json"))]
        for path in tables:
            if path.is_file():
                distance = None if path.parent == run else path.parent.name.removeprefix("distance-")
                found[key + (distance,)] = json.loads(path.read_text())["results"]
    return found


def write_figures(out: Path, panels: dict[str, dict[str, dict]], posteriors: dict[str, dict[str, dict]]) -> None:
    """``figures/accuracy.png`` (accuracy per setting, 95% intervals, the paper's P3 as ticks) from
    ``panels``, and ``figures/attributes.png`` (attribute recovery) and ``figures/reliability-V.png``
    (calibration per benchmark) from ``posteriors``: benchmark -> {row name: its evaluation results},
    one row per set of posteriors."""
    from .plots import accuracy_bars, attribute_bars, reliability_diagram

    names = [setting_name(n, k) for n, k in SETTINGS]
    accuracy = {TITLES[c]: {row: {n: (r["accuracy"][n]["mean"], r["accuracy"][n]["half_width"])
                                  for n in names if n in r["accuracy"]} for row, r in rows.items()}
                for c, rows in panels.items()}
    reference = {TITLES[c]: [float(v) for v in PAPER_ACCURACY["P3"][c].split("/")] for c in panels}
    accuracy_bars(out / "figures" / "accuracy.png", accuracy, names, reference)
    attributes = {TITLES[c]: {row: {name: r["attributes"][key] for key, name in ATTRIBUTES.items()
                                    if key in r["attributes"]}
                              for row, r in rows.items() if r.get("attributes")} for c, rows in posteriors.items()}
    attributes = {c: rows for c, rows in attributes.items() if rows}
    if attributes:
        attribute_bars(out / "figures" / "attributes.png", attributes)
    for c, rows in posteriors.items():
        if rows:
            reliability_diagram(out / "figures" / f"reliability-{c}.png", rows, names)


def write_paper_tables(out: Path, results: dict) -> None:
    """The accuracy and ADI tables in the paper's layout, from ``collect``'s runs, and their figures
    (:func:`write_figures`)."""
    variants = sorted({(s, d) for _, s, d in results}, key=lambda v: (_noise_order(v[0]), v[1] or ""))
    models = [(m, s, d) for s, d in variants for m in ("p3", "np3")
              if any(m in r for (_, *v), r in results.items() if tuple(v) == (s, d))]
    get = lambda c, m, s, d: results.get((c, s, d), {}).get(m)  # noqa: E731
    header = ["model", "source"] + [TITLES[c] for c in COLUMNS]
    rows = [[label(m, s, d), "this project"] + [cells(get(c, m, s, d)) if get(c, m, s, d) else "-" for c in COLUMNS]
            for m, s, d in models]
    found = {}
    for c in COLUMNS:        # baselines are scored into runs/V, whether or not it holds a P3 run
        for baseline in load_baselines(out / "runs" / c):
            found.setdefault(baseline["model"], {})[c] = baseline
    for model, per_benchmark in sorted(found.items()):
        rows.append([model, "this project"] + [cells(per_benchmark[c]) if c in per_benchmark else "-"
                                               for c in COLUMNS])
    for model, numbers in PAPER_ACCURACY.items():
        rows.append([model, "paper"] + [numbers[c] for c in COLUMNS])
    evaluated = [c for c in COLUMNS if any(v == c for v, _, _ in results)]
    write_figures(out, {c: {label(m, s, d): get(c, m, s, d) for m, s, d in models if get(c, m, s, d)}
                        | {model: per[c] for model, per in sorted(found.items()) if c in per} for c in evaluated},
                  # attributes depend on the posteriors only: one row per (model, noise), not per distance
                  {c: {label(m, s): get(c, m, s, None) for m, s, d in models if d is None and get(c, m, s, d)}
                   for c in evaluated})
    note = ("\nCells: 5-way 1-shot / 5-way 5-shot / 10-way 1-shot / 10-way 5-shot accuracy (%). "
            "OOD has 10 test classes. Rows without a note use the paper's likelihood (sigma 1, no outliers, no "
            "shadows); 'fitted noise' rows the Gaussian noise fitted to each benchmark's train residuals at the power "
            "1 / their correlation area, 'sandwich noise' rows the same Gaussian at the power along the object's "
            "outline (the composite likelihood's sandwich adjustment). Rows "
            "without distance terms use all seven of the paper's terms, over programs widened by the concept "
            "spread fitted on train classes unless marked 'no concept spread' (Student-t kernels whose tails are "
            "fitted there too, unless marked 'Gaussian concept kernels'), each KL turned round "
            "(KL(C_I || C_k)) unless marked 'KL(class || image)', the paper's direction. Sigma and distance "
            "terms were chosen on train classes, the "
            "spread, its tails and the KL's direction on held-out train classes. "
            "The paper's numbers are on its own data sets: compare in spirit.\n")
    atomic_write(out / "accuracy.md", markdown_table(header, rows) + note)
    with atomic_open(out / "accuracy.csv") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "sigma", "distance", "setting", "accuracy", "half_width_95", "ece",
                         "paper"])
        for c in COLUMNS:
            for m, s, d in models:
                if not get(c, m, s, d):
                    continue
                paper = PAPER_ACCURACY[m.upper()][c].split("/")
                for i, (n, k) in enumerate(SETTINGS):
                    a = get(c, m, s, d)["accuracy"].get(setting_name(n, k))
                    if a:
                        writer.writerow([c, m, "paper" if s is None else s, d or "paper", setting_name(n, k),
                                         a["mean"], a["half_width"], a["ece"], float(paper[i]) / 100])
    # ADI depends on the posteriors only, not on the distance: one column per (model, sigma)
    pose_models = [(m, s) for m, s, d in models if d is None]
    header = ["benchmark"] + [f"{label(m, s)} mean ADI (m)" for m, s in pose_models] + ["paper P3 / NP3"]
    adi = lambda c, m, s: f"{get(c, m, s, None)['adi']['mean']:.4f}" if get(c, m, s, None) else "-"  # noqa: E731
    rows = [[TITLES[c]] + [adi(c, m, s) for m, s in pose_models] + [f"{PAPER_ADI[c][0]:.4f} / {PAPER_ADI[c][1]:.4f}"]
            for c in evaluated]
    atomic_write(out / "adi.md", markdown_table(header, rows))
    with atomic_open(out / "adi.csv") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "sigma", "mean_adi_m", "median_adi_m", "paper_mean_adi_m"])
        for c in COLUMNS:
            for m, s in pose_models:
                if get(c, m, s, None):
                    a = get(c, m, s, None)["adi"]
                    writer.writerow([c, m, "paper" if s is None else s, a["mean"], a["median"],
                                     PAPER_ADI[c][("p3", "np3").index(m)]])
