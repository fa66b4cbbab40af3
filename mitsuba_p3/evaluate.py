"""End-to-end evaluation: test posteriors (cached), few-shot episodes, pose errors, tables.

``evaluate(dataset_dir, model_dir, run_dir)``

1. **Posteriors.** Every test image's posterior is sampled once per likelihood
   (P3, NP3) and cached as ``RUN/posteriors/LIKELIHOOD/INDEX.npz``: the property
   samples a protoprogram needs (thinned to ``keep_draws``), the point estimate
   and the diagnostics. Files are written atomically (temporary file, then
   rename), so a run killed at any moment resumes without recomputing finished
   images. ``RUN/run.json`` records the settings; a run folder refuses other
   settings. The per-image jobs run in parallel with joblib, or on a Dask
   cluster (joblib's Dask backend) when a scheduler address is given.
2. **Classification.** For every N-way K-shot setting, the same seeded episodes
   as every other model (:func:`mitsuba_p3.benchmarks.episodes.sample_episodes`);
   each class program merges its K support programs, each query is classified by
   :func:`mitsuba_p3.concepts.classify_many`. Accuracy per setting with a 95% interval
   over episodes (normal approximation), and the calibration of the class
   probabilities (expected calibration error over 10 bins; a reliability plot).
3. **Pose.** ADI (:mod:`mitsuba_p3.pose`) of every test image's posterior median
   position and modal yaw; mean and median per class and overall.

Outputs in RUN: ``accuracy.csv``/``.md``, ``adi.csv``/``.md``,
``reliability.png``, ``predictions.csv`` and ``results.json``. A distance with
other terms than the paper's (``DistanceConfig.properties``) reuses the run's
posteriors and writes its outputs to ``RUN/distance-TERMS`` (:func:`tables_dir`),
so the paper's tables are never overwritten.
"""
from __future__ import annotations

import json
import os
import tempfile
import time
from contextlib import ExitStack
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Callable

import numpy as np

from .benchmarks.dataset import Dataset, load_dataset
from .benchmarks.episodes import sample_episodes
from .concepts import CONTINUOUS, PROPERTIES, DistanceConfig, ProtoProgram, classify_many
from .errors import EvaluationError
from .infer.mcmc import SamplerConfig

SETTINGS = ((5, 1), (5, 5), (10, 1), (10, 5))
RUN_FORMAT = "mitsuba-p3-evaluation"



@dataclass
class EvaluationConfig:
    likelihoods: tuple = ("p3", "np3")
    sigma: float | None = None   # colour-likelihood sigma; None: the paper's (1.0; 0.35 for dark)
    renderer: str = "mitsuba"
    sampler: SamplerConfig = field(default_factory=SamplerConfig)
    episodes: int = 100          # per N-way K-shot setting
    queries_per_class: int = 1
    episode_seed: int = 0
    keep_draws: int = 2000       # posterior draws kept per image for its protoprogram
    distance: DistanceConfig = field(default_factory=DistanceConfig)
    jobs: int = 1                # joblib workers
    dask: str | None = None      # a Dask scheduler address: run the per-image jobs there

    def cache_key(self) -> dict:
        """The settings a cached posterior depends on."""
        return {"renderer": self.renderer, "sampler": asdict(self.sampler), "keep_draws": self.keep_draws,
                "sigma": self.sigma}


# ----------------------------------------------------------------------------- posteriors

def posterior_path(run_dir: Path, likelihood: str, index: int) -> Path:
    return Path(run_dir) / "posteriors" / likelihood / f"{index:05d}.npz"


def _atomic_savez(path: Path, **arrays) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    handle, temporary = tempfile.mkstemp(dir=path.parent, suffix=".tmp.npz")
    os.close(handle)
    try:
        np.savez(temporary, **arrays)
        os.replace(temporary, path)
    finally:
        if os.path.exists(temporary):
            os.remove(temporary)


# XLA's CPU client reads these when it starts: one thread for its own work
SINGLE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def worker_threads(jobs: int) -> int | None:
    """Threads per worker process when ``jobs`` share this machine, or None to keep the defaults.

    Every worker's Dr.Jit and XLA otherwise start one thread per core, and the
    oversubscribed workers slow each other down. Measured on the 2-core machine, P3
    posteriors at the evaluation preset: one process with 2 threads 10.4 s per image;
    two processes with 2 threads each about 29 s each (14.5 s per image); two
    processes with one thread each 14.5 s each (7.3 s per image, 1.4x the throughput
    of one process)."""
    if jobs <= 1:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // jobs)


def _limit_threads(threads: int) -> None:
    """Give this worker process ``threads`` threads for rendering (Dr.Jit) and, for one thread, a
    single-threaded XLA. A fresh worker has not imported JAX yet when its first job starts (this
    module does not import it), so the XLA flags take effect."""
    from .backend import mitsuba

    mitsuba()  # Dr.Jit with the checked libLLVM
    import drjit as dr

    if threads == 1:
        os.environ.setdefault("XLA_FLAGS", SINGLE_THREAD_XLA_FLAGS)
    if dr.thread_count() != threads:
        dr.set_thread_count(threads)


def _render_threads() -> int:
    import drjit as dr

    return dr.thread_count()


def posterior_job(dataset_dir: str, model_dir: str, index: int, likelihood: str, renderer: str,
                  sampler: dict, keep_draws: int, out: str, sigma: float | None = None,
                  threads: int | None = None) -> str:
    """Sample one image's posterior and cache what evaluation needs (a picklable job)."""
    if threads:
        _limit_threads(threads)
    from .fit.model import FittedModel
    from .infer.posterior import default_likelihood, infer_image

    dataset = load_dataset(dataset_dir)
    shot = dataset.shots[index]
    fitted = FittedModel(model_dir)
    start = time.perf_counter()
    posterior = infer_image(fitted, dataset.image(shot), default_likelihood(fitted, likelihood, sigma),
                            SamplerConfig(**sampler), renderer=renderer)
    seconds = time.perf_counter() - start
    estimate = posterior.estimate()
    summary = posterior.summary()
    draws = len(posterior.draws("kappa"))
    keep = np.linspace(0, draws - 1, min(keep_draws, draws)).astype(int)
    samples = {f"sample_{name}": posterior.draws(name).reshape(draws, -1)[keep].astype(np.float32)
               for name in CONTINUOUS}
    _atomic_savez(Path(out), **samples, sample_class=posterior.draws("kappa")[keep].astype(np.int8),
                  shift=np.asarray(estimate["shift"], np.float64), yaw=np.float64(estimate["theta"]),
                  kappa=np.int64(estimate["kappa"]), seconds=np.float64(seconds),
                  max_r_hat=np.float64(summary["r_hat"].max()), min_ess=np.float64(summary["ess_bulk"].min()),
                  render_threads=np.int64(_render_threads()))
    return out


@dataclass
class CachedPosterior:
    """What evaluation keeps of one image's posterior."""

    program: ProtoProgram
    shift: np.ndarray
    yaw: float
    kappa: int
    seconds: float
    max_r_hat: float
    min_ess: float

    @classmethod
    def load(cls, path: Path, max_points: int) -> "CachedPosterior":
        with np.load(path) as f:
            samples = {name: f[f"sample_{name}"].astype(np.float64) for name in CONTINUOUS}
            samples["class"] = f["sample_class"].astype(int)
            return cls(ProtoProgram(samples, max_points), f["shift"], float(f["yaw"]), int(f["kappa"]),
                       float(f["seconds"]), float(f["max_r_hat"]), float(f["min_ess"]))


def check_run(run_dir: Path, dataset: Dataset, model_dir: Path, config: EvaluationConfig) -> None:
    """Create RUN/run.json, or refuse a folder made with other settings or another data set."""
    record = {"format": RUN_FORMAT, "version": 1, "dataset": str(Path(dataset.root).resolve()),
              "model": str(Path(model_dir).resolve()), **config.cache_key()}
    path = run_dir / "run.json"
    if path.exists():
        previous = json.loads(path.read_text())
        changed = [k for k in record if k not in ("dataset", "model") and previous.get(k) != record[k]]
        if previous.get("format") != RUN_FORMAT or changed:
            raise EvaluationError(f"{run_dir} holds an evaluation with other settings ({', '.join(changed)}); "
                                  "use another --out folder or remove it")
        return
    run_dir.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(record, indent=1, default=str))


def compute_posteriors(dataset: Dataset, model_dir: Path, run_dir: Path, config: EvaluationConfig,
                       progress: Callable[[int, int], None] | None = None,
                       shots: list[int] | None = None) -> None:
    """Sample every missing test posterior (or those of ``shots``, indices into ``dataset.shots``)
    with joblib, or on Dask when ``config.dask`` is set."""
    from joblib import Parallel, delayed, parallel_config

    tests = dataset.split("test") if shots is None else [dataset.shots[i] for i in shots]
    todo = [(shot.index, likelihood) for likelihood in config.likelihoods for shot in tests
            if not posterior_path(run_dir, likelihood, shot.index).exists()]
    total = len(tests) * len(config.likelihoods)
    done = total - len(todo)
    if progress:
        progress(done, total)
    if not todo:
        return
    threads = None if config.dask else worker_threads(config.jobs)
    jobs = (delayed(posterior_job)(str(dataset.root), str(model_dir), index, likelihood, config.renderer,
                                   asdict(config.sampler), config.keep_draws,
                                   str(posterior_path(run_dir, likelihood, index)), config.sigma, threads)
            for index, likelihood in todo)
    with ExitStack() as stack:
        if config.dask:
            from dask.distributed import Client

            stack.enter_context(Client(config.dask))
            stack.enter_context(parallel_config(backend="dask"))
        for _ in Parallel(n_jobs=None if config.dask else config.jobs, return_as="generator_unordered")(jobs):
            done += 1
            if progress:
                progress(done, total)


# ----------------------------------------------------------------------------- scores

def interval95(values) -> tuple[float, float]:
    """Mean and the half-width of its 95% normal-approximation interval."""
    values = np.asarray(values, np.float64)
    half = 1.96 * values.std(ddof=1) / np.sqrt(len(values)) if len(values) > 1 else float("nan")
    return float(values.mean()), float(half)


def expected_calibration_error(confidence: np.ndarray, correct: np.ndarray, bins: int = 10) -> tuple[float, list]:
    """ECE over equal-width confidence bins, and the bins' (mean confidence, accuracy, count)."""
    confidence, correct = np.asarray(confidence, float), np.asarray(correct, float)
    edges = np.linspace(0.0, 1.0, bins + 1)
    which = np.clip(np.digitize(confidence, edges[1:-1]), 0, bins - 1)
    ece, table = 0.0, []
    for b in range(bins):
        members = which == b
        if members.any():
            gap = abs(correct[members].mean() - confidence[members].mean())
            ece += members.mean() * gap
            table.append((float(confidence[members].mean()), float(correct[members].mean()), int(members.sum())))
        else:
            table.append((float("nan"), float("nan"), 0))
    return float(ece), table


def classify_episodes(dataset: Dataset, cached: dict[int, CachedPosterior], n_way: int, k_shot: int,
                      config: EvaluationConfig) -> list[dict]:
    """Predictions for every query of the setting's episodes."""
    rows = []
    for number, episode in enumerate(sample_episodes(dataset, n_way, k_shot, config.episodes, config.episode_seed,
                                                     config.queries_per_class)):
        programs = [ProtoProgram.merge([cached[i].program for i in shots]) for shots in episode.support]
        every = classify_many(programs, [cached[index].program for index, _ in episode.queries], config.distance)
        for (index, truth), probabilities in zip(episode.queries, every):
            rows.append({"n_way": n_way, "k_shot": k_shot, "episode": number, "query": index, "truth": truth,
                         "predicted": int(np.argmax(probabilities)), "confidence": float(probabilities.max()),
                         "p_true": float(probabilities[truth])})
    return rows


def one_shot_accuracy(programs: dict[str, list[ProtoProgram]], n_way: int, episodes: int, seed: int,
                      config: DistanceConfig) -> float:
    """Mean accuracy of seeded N-way 1-shot episodes over the classes of ``programs`` (class -> its
    shots' programs, 2 or more): per chosen class one shot is the support, another the query. For
    choices made on train classes (``scripts/select_sigma.py``, ``scripts/select_distance.py``)."""
    rng = np.random.default_rng([seed, n_way])
    names = sorted(programs)
    correct = []
    for _ in range(episodes):
        chosen = [names[i] for i in rng.choice(len(names), size=n_way, replace=False)]
        pairs = [rng.choice(len(programs[c]), size=2, replace=False) for c in chosen]
        support = [programs[c][s] for c, (s, _) in zip(chosen, pairs)]
        queries = [programs[c][q] for c, (_, q) in zip(chosen, pairs)]
        probabilities = classify_many(support, queries, config)
        correct += list(np.argmax(probabilities, axis=1) == np.arange(n_way))
    return float(np.mean(correct))


def pose_errors(dataset: Dataset, cached: dict[int, CachedPosterior]) -> list[dict]:
    from .pose import adi

    return [{"query": index, "class": dataset.shots[index].cls.name,
             "adi": adi(dataset.shots[index], post.shift, post.yaw)} for index, post in cached.items()]


# ----------------------------------------------------------------------------- tables

def tables_dir(run_dir: Path, distance: DistanceConfig) -> Path:
    """Where a run's tables for ``distance`` go: the run folder for the paper's distance (all
    terms), ``RUN/distance-colour+class`` (say) for another, its terms in the order of
    ``PROPERTIES`` (the distance is their sum); the posteriors are shared."""
    terms = [p for p in PROPERTIES if p in distance.properties]
    if tuple(terms) == PROPERTIES:
        return Path(run_dir)
    return Path(run_dir) / ("distance-" + "+".join(terms))


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows]) + "\n"


def write_tables(run_dir: Path, results: dict, baselines_dir: Path | None = None) -> dict:
    """accuracy / adi / calibration as CSV and markdown, and the reliability plot, in ``run_dir``;
    baselines evaluated into ``baselines_dir`` (default ``run_dir``) join the accuracy table."""
    import csv

    settings = [f"{n}-way {k}-shot" for n, k in SETTINGS]
    header = ["model"] + settings
    rows = []
    for likelihood, result in results.items():
        cells = []
        for name in settings:
            acc = result["accuracy"].get(name)
            cells.append(f"{100 * acc['mean']:.1f} ± {100 * acc['half_width']:.1f}" if acc else "-")
        rows.append([likelihood.upper()] + cells)
    baselines = load_baselines(baselines_dir or run_dir)
    for baseline in baselines:
        rows.append([baseline["model"]] + [
            f"{100 * a['mean']:.1f} ± {100 * a['half_width']:.1f}" if (a := baseline["accuracy"].get(name)) else "-"
            for name in settings])
    (run_dir / "accuracy.md").write_text(markdown_table(header, rows))
    with open(run_dir / "accuracy.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "setting", "accuracy", "half_width_95", "episodes", "ece"])
        for likelihood, result in results.items():
            for name, acc in result["accuracy"].items():
                writer.writerow([likelihood, name, acc["mean"], acc["half_width"], acc["episodes"], acc["ece"]])
        for baseline in baselines:
            for name, acc in baseline["accuracy"].items():
                writer.writerow([baseline["model"], name, acc["mean"], acc["half_width"], acc["episodes"], ""])

    classes = sorted({c for result in results.values() for c in result["adi_per_class"]})
    adi_rows = [[c] + [f"{result['adi_per_class'][c]['mean']:.4f} / {result['adi_per_class'][c]['median']:.4f}"
                       for result in results.values()] for c in classes]
    adi_rows.append(["**all**"] + [f"{r['adi']['mean']:.4f} / {r['adi']['median']:.4f}" for r in results.values()])
    (run_dir / "adi.md").write_text(markdown_table(["class"] + [f"{k.upper()} mean / median (m)" for k in results],
                                              adi_rows))
    with open(run_dir / "adi.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "class", "mean_adi_m", "median_adi_m", "images"])
        for likelihood, result in results.items():
            for c, v in result["adi_per_class"].items():
                writer.writerow([likelihood, c, v["mean"], v["median"], v["images"]])
            writer.writerow([likelihood, "all", result["adi"]["mean"], result["adi"]["median"],
                             result["adi"]["images"]])
    _reliability_plot(run_dir / "reliability.png", results)
    return {"accuracy": str(run_dir / "accuracy.md"), "adi": str(run_dir / "adi.md"),
            "reliability": str(run_dir / "reliability.png")}


def load_baselines(run_dir: Path) -> list[dict]:
    """Baseline results evaluated on this run's episodes (``mitsuba-p3 baseline evaluate --out RUN``)."""
    return [json.loads(p.read_text()) for p in sorted(Path(run_dir).glob("baselines/*.json"))]


def _reliability_plot(path: Path, results: dict) -> None:
    from .plots import save_figure

    import matplotlib.pyplot as plt

    settings = [f"{n}-way {k}-shot" for n, k in SETTINGS
                if any(f"{n}-way {k}-shot" in r["accuracy"] for r in results.values())]
    figure, axes = plt.subplots(1, len(settings), figsize=(3.2 * len(settings), 3.2), squeeze=False)
    for ax, name in zip(axes[0], settings):
        ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--")
        for likelihood, result in results.items():
            acc = result["accuracy"].get(name)
            if not acc:
                continue
            bins = [b for b in acc["reliability"] if b[2] > 0]
            ax.plot([b[0] for b in bins], [b[1] for b in bins], marker="o",
                    label=f"{likelihood.upper()} (ECE {acc['ece']:.3f})")
        ax.set_title(name)
        ax.set_xlabel("confidence")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="upper left")
    axes[0][0].set_ylabel("accuracy")
    save_figure(figure, path)


# ----------------------------------------------------------------------------- driver

def evaluate(dataset_dir: str | Path, model_dir: str | Path, run_dir: str | Path,
             config: EvaluationConfig | None = None,
             progress: Callable[[str, int, int], None] | None = None) -> dict:
    """Posteriors (resumable), episodes, pose errors and tables; returns the results."""
    import csv

    config = config or EvaluationConfig()
    dataset = load_dataset(dataset_dir)
    run_dir = Path(run_dir)
    check_run(run_dir, dataset, Path(model_dir), config)
    compute_posteriors(dataset, Path(model_dir), run_dir, config,
                       (lambda done, total: progress("posteriors", done, total)) if progress else None)
    n_classes = len(dataset.classes("test"))
    fewest = min(len(dataset.shots_of(c)) for c in dataset.classes("test"))
    settings = [(n, k) for n, k in SETTINGS if n <= n_classes and k + config.queries_per_class <= fewest]
    results, predictions = {}, []
    for likelihood in config.likelihoods:
        cached = {shot.index: CachedPosterior.load(posterior_path(run_dir, likelihood, shot.index),
                                                   config.distance.max_points)
                  for shot in dataset.split("test")}
        accuracy = {}
        for step, (n_way, k_shot) in enumerate(settings):
            if progress:
                progress(f"episodes {likelihood}", step, len(settings))
            rows = classify_episodes(dataset, cached, n_way, k_shot, config)
            if progress:
                progress(f"episodes {likelihood}", step + 1, len(settings))
            for row in rows:
                row["model"] = likelihood
            predictions += rows
            per_episode = [np.mean([r["predicted"] == r["truth"] for r in rows if r["episode"] == e])
                           for e in range(config.episodes)]
            mean, half = interval95(per_episode)
            ece, bins = expected_calibration_error([r["confidence"] for r in rows],
                                                   [r["predicted"] == r["truth"] for r in rows])
            accuracy[f"{n_way}-way {k_shot}-shot"] = {"mean": mean, "half_width": half,
                                                      "episodes": config.episodes, "ece": ece, "reliability": bins}
        errors = pose_errors(dataset, cached)
        per_class = {}
        for name in sorted({e["class"] for e in errors}):
            values = [e["adi"] for e in errors if e["class"] == name]
            per_class[name] = {"mean": float(np.mean(values)), "median": float(np.median(values)),
                               "images": len(values)}
        values = [e["adi"] for e in errors]
        results[likelihood] = {
            "accuracy": accuracy, "adi_per_class": per_class,
            "adi": {"mean": float(np.mean(values)), "median": float(np.median(values)), "images": len(values)},
            "seconds_per_image": float(np.mean([c.seconds for c in cached.values()])),
            "max_r_hat_median": float(np.median([c.max_r_hat for c in cached.values()])),
        }
    out = tables_dir(run_dir, config.distance)
    out.mkdir(parents=True, exist_ok=True)
    with open(out / "predictions.csv", "w", newline="") as f:
        if predictions:
            writer = csv.DictWriter(f, fieldnames=list(predictions[0]))
            writer.writeheader()
            writer.writerows(predictions)
    files = write_tables(out, results, baselines_dir=run_dir)
    (out / "results.json").write_text(json.dumps({"dataset": str(dataset.root), "results": results,
                                                  "distance": list(config.distance.properties),
                                                  "files": files}, indent=1))
    return results
