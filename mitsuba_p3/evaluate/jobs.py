"""Per-image posterior jobs and their cache: run in parallel (worker processes or Dask), resumable after a kill.

Every test image's posterior is sampled once per likelihood and cached as
``RUN/posteriors/LIKELIHOOD/INDEX.npz``: the property samples a protoprogram
needs (thinned to ``keep_draws``), the point estimate and the diagnostics.
Files are written atomically, so a run killed at any moment resumes without
recomputing finished images. ``RUN/run.json`` records the settings; a run folder
refuses other settings.
"""
from __future__ import annotations

import json
import os
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Callable

import numpy as np

from ..benchmarks.dataset import Dataset, load_dataset
from ..concepts import CONTINUOUS, ProtoProgram
from ..errors import EvaluationError
from ..files import atomic_json, atomic_npz, claim_output_folder, file_digest
from .config import EvaluationConfig

RUN_FORMAT = "mitsuba-p3-evaluation"


def posterior_path(run_dir: Path, likelihood: str, index: int) -> Path:
    return Path(run_dir) / "posteriors" / likelihood / f"{index:05d}.npz"


# XLA's CPU client reads these when it starts: one thread for its own work
SINGLE_THREAD_XLA_FLAGS = "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1"


def worker_threads(jobs: int) -> int | None:
    """Threads per worker process when ``jobs`` share this machine, or None to keep the defaults.

    Every worker's Dr.Jit and XLA otherwise start one thread per core, and the
    oversubscribed workers slow each other down: the cores are shared out instead."""
    if jobs <= 1:
        return None
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
    return max(1, cores // jobs)


def _limit_threads(threads: int, renderer: str = "mitsuba") -> None:
    """Give this worker process ``threads`` threads for rendering (Dr.Jit) and, for one thread, a
    single-threaded XLA. A fresh worker has not imported JAX yet when its first job starts (this
    module does not import it), so the XLA flags take effect. Workers that share a GPU each take
    its memory as they need it rather than XLA's default three quarters of the device at start, which
    no two workers can both take. Under the JAX tracer Dr.Jit renders nothing and is left alone: such an
    evaluation runs where Mitsuba is not installed."""
    flags = os.environ.get("XLA_FLAGS", "")
    if threads == 1 and "multi_thread_eigen" not in flags:     # a user's own thread flags rule
        os.environ["XLA_FLAGS"] = f"{flags} {SINGLE_THREAD_XLA_FLAGS}".strip()
    os.environ.setdefault("XLA_PYTHON_CLIENT_PREALLOCATE", "false")
    if renderer != "mitsuba":
        return
    from ..backend import mitsuba

    mitsuba()  # Dr.Jit with the checked libLLVM
    import drjit as dr

    if dr.thread_count() != threads:
        dr.set_thread_count(threads)


_WATCHED = False


def _exit_with_parent() -> None:
    """In a worker process: exit as soon as the process that started it is gone (a killed
    ``evaluate`` must not leave its workers computing, then idling at a gigabyte each). A daemon
    thread polls the parent's pid once a second; started once per worker."""
    import threading

    global _WATCHED
    if _WATCHED:
        return
    _WATCHED = True
    parent = os.getppid()

    def watch():
        while os.getppid() == parent:
            time.sleep(1.0)
        os._exit(1)

    threading.Thread(target=watch, name="exit-with-parent", daemon=True).start()


def _render_threads(renderer: str = "mitsuba") -> int:
    """Dr.Jit's render threads in this process; 0 where the JAX tracer renders (XLA's own threads)."""
    if renderer != "mitsuba":
        return 0
    import drjit as dr

    return dr.thread_count()


def posterior_job(dataset_dir: str, model_dir: str, index: int, likelihood: str, config: EvaluationConfig,
                  out: str, threads: int | None = None) -> str:
    """Sample one image's posterior and cache what evaluation needs (a picklable job)."""
    if threads:                    # a worker process of this machine (:func:`in_workers`)
        _exit_with_parent()
        _limit_threads(threads, config.renderer)
    from ..fit.model import FittedModel
    from ..infer.posterior import default_likelihood, sample_posterior

    dataset = load_dataset(dataset_dir)
    shot = dataset.shots[index]
    fitted = FittedModel(model_dir)
    # a bridged NP3 run starts from P3's particles of the same image when P3's job cached them
    # (else sample_posterior runs P3 first: the same particles, since the sampler is seeded)
    bridged = likelihood == "np3" and getattr(config.sampler, "bridge", False)
    start_from = _cached_particles(posterior_path(Path(out).parents[2], "p3", index)) if bridged else None
    start = time.perf_counter()
    posterior = sample_posterior(fitted, dataset.image(shot), default_likelihood(fitted, likelihood, config.sigma, config.noise),
                            config.sampler, renderer=config.renderer, start=start_from)
    seconds = time.perf_counter() - start
    estimate = posterior.estimate()
    summary = posterior.summary()
    gap = posterior.statistic("island_gap")     # SMC only: None for MH or a single run
    factor = posterior.statistic("log_bayes_factor_object")     # SMC only: one object against the empty floor
    draws = len(posterior.draws("kappa"))
    keep = np.linspace(0, draws - 1, min(config.keep_draws, draws)).astype(int)
    samples = {f"sample_{name}": posterior.draws(name).reshape(draws, -1)[keep].astype(np.float32)
               for name in CONTINUOUS}
    atomic_npz(Path(out), **samples, image_digest=np.array(image_digest(shot)),
               sample_class=posterior.draws("kappa")[keep].astype(np.int8),
               sample_shift=posterior.draws("shift")[keep].astype(np.float32),
                  shift=np.asarray(estimate["shift"], np.float64), yaw=np.float64(estimate["theta"]),
                  kappa=np.int64(estimate["kappa"]), seconds=np.float64(seconds),
                  max_r_hat=np.float64(summary["r_hat"].max()), min_ess=np.float64(summary["ess_bulk"].min()),
                  island_gap=np.float64(np.nan if gap is None else gap),
                  log_bayes_factor_object=np.float64(np.nan if factor is None else factor),
                  render_threads=np.int64(_render_threads(config.renderer)), **_evidence(posterior),
                  **(_particle_arrays(posterior.particles) if likelihood == "p3" else {}))
    return out


def _particle_arrays(particles) -> dict:
    """An SMC run's final particles as arrays of the cache file (none for MH): what a bridged
    NP3 run of the same image starts from."""
    if particles is None:
        return {}
    rows = particles.rows
    return {"particles_index": np.asarray(rows.index, np.int64),
            "particles_position": np.asarray(rows.state.position, np.float32),
            "particles_loglikelihood": np.asarray(rows.state.loglikelihood, np.float32),
            "particles_logprior": np.asarray(rows.state.logprior, np.float32),
            "particles_log_evidence": np.asarray(rows.log_evidence, np.float64),
            "particles_temperatures": np.int64(rows.temperatures),
            "particles_window": np.asarray(particles.window if particles.window else [], np.int64),
            # with the importance-sampling evidence: each run's tempered estimate beside the kept one
            **({} if rows.tempered is None else
               {"particles_log_evidence_tempered": np.asarray(rows.tempered, np.float64),
                "particles_log_evidence_importance": np.asarray(rows.importance, np.float64)})}


def _cached_particles(path: Path):
    """The SMC particles a cached P3 posterior kept, or None (no file, an MH run, an older cache)."""
    from ..infer.smc import Particles, Rows, SMCState

    if not path.exists():
        return None
    try:
        with np.load(path) as f:
            if "particles_position" not in f.files:
                return None
            window = tuple(int(v) for v in f["particles_window"]) or None
            state = SMCState(f["particles_position"], f["particles_loglikelihood"], f["particles_logprior"])
            rows = Rows(f["particles_index"], state, f["particles_log_evidence"], int(f["particles_temperatures"]), [])
    except Exception:                      # a damaged file: P3's own job will set it aside (_cached)
        return None
    return Particles(rows, window)


def _evidence(posterior) -> dict:
    """Per hypothesis log evidence, when the sampler estimated it (SMC)."""
    hypotheses = posterior.idata.posterior.attrs.get("hypotheses")
    if hypotheses is None:
        return {}
    values = json.loads(hypotheses) if isinstance(hypotheses, str) else hypotheses
    return {"log_evidence": np.array([v["log_evidence"] for v in values.values()], np.float64)}


@dataclass
class CachedPosterior:
    """What evaluation keeps of one image's posterior."""

    program: ProtoProgram
    shift: np.ndarray
    yaw: float
    kappa: int
    seconds: float
    max_r_hat: float              # across MH chains (NaN for SMC: one pool has no R-hat)
    min_ess: float
    log_evidence: np.ndarray | None = None       # per hypothesis the SMC weighed (shape classes by default)
    shift_samples: np.ndarray | None = None      # (n, 2) posterior draws of the position (newer caches)
    island_gap: float = float("nan")             # SMC: spread of the leading hypothesis's runs' log Z (nats)
    log_bayes_factor_object: float = float("nan")  # SMC: one object against the empty floor (< 0: nothing)

    @property
    def pose(self) -> dict:
        """The point estimate's pose: position, yaw, median half-extents and modal class."""
        return {"shift": np.asarray(self.shift, np.float64), "theta": float(self.yaw),
                "scale": np.median(self.program.samples["scale"], axis=0), "kappa": int(self.kappa)}

    @classmethod
    def load(cls, path: Path, max_points: int) -> "CachedPosterior":
        with np.load(path) as f:
            samples = {name: f[f"sample_{name}"].astype(np.float64) for name in CONTINUOUS}
            samples["class"] = f["sample_class"].astype(int)
            return cls(ProtoProgram(samples, max_points), f["shift"], float(f["yaw"]), int(f["kappa"]),
                       float(f["seconds"]), float(f["max_r_hat"]), float(f["min_ess"]),
                       f["log_evidence"] if "log_evidence" in f.files else None,
                       f["sample_shift"].astype(np.float64) if "sample_shift" in f.files else None,
                       float(f["island_gap"]) if "island_gap" in f.files else float("nan"),
                       float(f["log_bayes_factor_object"]) if "log_bayes_factor_object" in f.files else float("nan"))


def cached_train_posteriors(dataset: Dataset, run_dir: Path, likelihood: str,
                            max_points: int = 500) -> dict[str, dict[int, CachedPosterior]]:
    """Every cached train posterior of a run, by class and image index (for choices made on train classes)."""
    posteriors = {}
    for name in dataset.classes("train"):
        paths = {shot.index: posterior_path(run_dir, likelihood, shot.index) for shot in dataset.shots_of(name)}
        posteriors[name] = {index: CachedPosterior.load(path, max_points) for index, path in paths.items()
                            if path.exists()}
    return posteriors


def cached_train_programs(dataset: Dataset, run_dir: Path, likelihood: str,
                          max_points: int = 500) -> dict[str, list[ProtoProgram]]:
    """The programs of every cached train posterior of a run, by class (for choices made on train classes)."""
    return {name: [p.program for p in posteriors.values()]
            for name, posteriors in cached_train_posteriors(dataset, run_dir, likelihood, max_points).items()}


class PosteriorMisfits:
    """The Phong misfit (:func:`mitsuba_p3.infer.misfit.phong_misfit`) of cached posteriors of one data
    set at their pose estimates, in units of the model's fitted noise; one renderer, values kept by
    image index and pose. ``available`` is False for a model fitted without the noise stage (no unit to
    measure in), and the material rule then does without the misfit."""

    def __init__(self, dataset: Dataset, model_dir: Path):
        from ..fit.model import FittedModel

        self.dataset = dataset
        self.fitted = FittedModel(model_dir)
        self.available = (self.fitted.root / "noise.json").exists()
        self._renderer = None
        self._values: dict[tuple, float] = {}

    def __call__(self, index: int, posterior: CachedPosterior) -> float:
        from ..infer.misfit import misfit_renderer, model_misfit

        pose = posterior.pose
        key = (index, *pose["shift"], pose["theta"], *pose["scale"], pose["kappa"])
        if key not in self._values:
            if self._renderer is None:
                self._renderer = misfit_renderer(self.fitted, *self.dataset.resolution)
            self._values[key] = model_misfit(self.fitted, self.dataset.image(self.dataset.shots[index]), pose,
                                             self._renderer)
        return self._values[key]

    def for_rules(self, rules, index: int, posterior: CachedPosterior) -> float | None:
        """The posterior's misfit when ``rules``' material model reads it, else None (no render)."""
        return self(index, posterior) if rules.reads_misfit else None


# The material rule's features, chosen on train classes, each class held out in turn: the Phong weights,
# the reflectance's saturation and the Phong misfit (what Phong cannot render, not a colour, so it reads the
# same on every set).
MATERIAL_RULE_FEATURES = "weights+saturation+misfit"


def rules_with_train_posteriors(rules, dataset: Dataset, run_dir: Path, likelihood: str,
                                misfits: PosteriorMisfits | None = None):
    """The attribute rules with the material kind learnt from the run's cached *train* posteriors
    (:meth:`~mitsuba_p3.fit.attributes.AttributeRules.with_material_from_posteriors`, on
    :data:`MATERIAL_RULE_FEATURES`, or without the misfit when ``misfits`` is None or unavailable),
    when it holds posteriors of both kinds, and the colour centres moved to those posteriors' (:meth:`~mitsuba_p3.
    fit.attributes.AttributeRules.with_colours_from_posteriors`). Chosen on train classes: learnt from
    posteriors, the material rule beats the one learnt from the fit's materials, and the colour centres read every train colour under the
    fit's kept start where the fit's own centres can be tinted."""
    posteriors = cached_train_posteriors(dataset, run_dir, likelihood)
    learnt = rules_learnt_from(rules, posteriors, dataset.class_labels, MATERIAL_RULE_FEATURES, misfits)
    return colours_learnt_from(learnt, posteriors, dataset.class_labels)


def colours_learnt_from(rules, posteriors: dict[str, dict[int, CachedPosterior]], labels: dict):
    """``rules`` with the colour centres moved to these train posteriors' (by class name and image index;
    ``labels`` give each class's colour and kind); unchanged without posteriors."""
    pairs = [(name, post) for name, group in posteriors.items() for post in group.values()]
    if not pairs:
        return rules
    return rules.with_colours_from_posteriors([post.program.samples for _, post in pairs],
                                              [labels[name].colour for name, _ in pairs],
                                              [labels[name].material for name, _ in pairs])


def rules_learnt_from(rules, posteriors: dict[str, dict[int, CachedPosterior]], labels: dict,
                      features: str = "weights", misfits: PosteriorMisfits | None = None):
    """``rules`` with the material kind learnt from these train posteriors (by class name and image
    index; ``labels`` give each class's kind) on ``features``; unchanged without posteriors of both
    kinds. Features that need the Phong misfit drop it when ``misfits`` is None or unavailable."""
    if features.endswith("+misfit") and (misfits is None or not misfits.available):
        features = features[:-len("+misfit")]
    pairs = [(name, index, post) for name, group in posteriors.items() for index, post in group.items()]
    values = [misfits(index, post) for _, index, post in pairs] if features.endswith("+misfit") else None
    return rules.with_material_from_posteriors([post.program.samples for _, _, post in pairs],
                                               [labels[name].material for name, _, _ in pairs], features, values)


def check_run(run_dir: Path, dataset: Dataset, model_dir: Path, config: EvaluationConfig) -> None:
    """Create RUN/run.json, or refuse a folder whose cached posteriors were made with other settings or
    from another data set or model. A run that died before caching its first posterior holds nothing
    to protect: its record is replaced, so the corrected command simply starts again."""
    record = {"format": RUN_FORMAT, "version": 1, "benchmark": dataset.variant,
              "dataset": str(Path(dataset.root).resolve()),
              "model": str(Path(model_dir).resolve()), **config.cache_key(),
              # the files' contents too: a model fitted again, or labels rewritten, in the same folder
              "model_digest": file_digest(Path(model_dir) / "model.json"),
              "labels_digest": file_digest(Path(dataset.root) / "labels.json")}
    record = json.loads(json.dumps(record))   # as the file holds it (a tuple setting reads back as a list)
    # a run folder may already hold baselines scored on the same episodes (mitsuba-p3 baseline evaluate)
    claim_output_folder(run_dir, ("run.json", "baselines"), "mitsuba-p3 evaluate")
    path = run_dir / "run.json"
    if path.exists():
        try:
            previous = json.loads(path.read_text())
        except ValueError:
            previous = None
        if not isinstance(previous, dict) or previous.get("format") != RUN_FORMAT:
            raise EvaluationError(f"{path} is not a {RUN_FORMAT} record; use another --out folder")
        if not any((run_dir / "posteriors").glob("*/*.npz")):
            atomic_json(path, record)
            return
        for source, digest in (("dataset", "labels_digest"), ("model", "model_digest")):
            # a record from before the digests were kept is checked by the folder's name alone
            moved = previous.get(source) != record[source]
            if moved or previous.get(digest, record[digest]) != record[digest]:
                raise EvaluationError(f"{run_dir} holds posteriors of another {source} ({previous.get(source)}"
                                      f"{'' if moved else ', changed since'}); use another --out folder or remove it")
        if isinstance(previous.get("sampler"), dict) and "particles" in previous["sampler"]:
            previous["sampler"].setdefault("bridge", False)     # an SMC record from before the bridge
        if isinstance(previous.get("sampler"), dict):
            # a setting added to the sampler after the record was written was, at its default then, not in play
            previous["sampler"] = {**_sampler_defaults(previous["sampler"]), **previous["sampler"]}
        if _np3_start_changed(previous, record):
            # the bridge decides how NP3's posteriors were made, and nothing of P3's
            if "np3" not in config.likelihoods:
                return
            if not any((run_dir / "posteriors" / "np3").glob("*.npz")):
                atomic_json(path, record)
                return
            raise EvaluationError(f"{run_dir} holds NP3 posteriors made with the SMC's bridge "
                                  f"{'on' if _bridge(previous) else 'off'}; pass --bridge/--no-bridge to match, "
                                  f"or remove {run_dir / 'posteriors' / 'np3'} to sample them again")
        changed = [k for k in record if k not in ("benchmark", "dataset", "model", "model_digest", "labels_digest")
                   and previous.get(k) != record[k]]
        if changed:
            raise EvaluationError(f"{run_dir} holds an evaluation with other settings ({', '.join(changed)}); "
                                  "use another --out folder or remove it")
        return
    atomic_json(path, record)


def _sampler_defaults(sampler: dict) -> dict:
    """Every field of the sampler config a run record's sampler is (SMC if it has particles), at the
    default it had before the field existed, as run.json holds it."""
    from dataclasses import asdict

    from ..infer.mcmc import SamplerConfig
    from ..infer.smc import DEFAULTS_BEFORE, SMCConfig

    if "particles" not in sampler:
        return json.loads(json.dumps(asdict(SamplerConfig())))
    return json.loads(json.dumps({**asdict(SMCConfig()), **DEFAULTS_BEFORE}))


def _bridge(record: dict):
    """A run record's SMC bridge setting; None for MH."""
    sampler = record.get("sampler") or {}
    return sampler.get("bridge") if "particles" in sampler else None


def _np3_start_changed(previous: dict, record: dict) -> bool:
    """Whether two run records differ in the SMC's bridge and nothing else."""
    if _bridge(previous) is None or _bridge(record) is None or _bridge(previous) == _bridge(record):
        return False
    strip = lambda r: {**r, "sampler": {k: v for k, v in r["sampler"].items() if k != "bridge"}}  # noqa: E731
    ignored = ("benchmark", "dataset", "model", "model_digest", "labels_digest")
    return all(strip(previous).get(k) == strip(record)[k] for k in record if k not in ignored)


def check_scheduler(address: str) -> None:
    """Refuse, in seconds rather than after Dask's 30 s timeout, a scheduler nobody listens at."""
    import socket
    from urllib.parse import urlparse

    parsed = urlparse(address if "://" in address else f"tcp://{address}")
    try:
        port = parsed.port
    except ValueError:
        port = None
    if not parsed.hostname or port is None:
        raise EvaluationError(f"--dask must be a scheduler address such as tcp://host:8786; got {address!r}")
    try:
        socket.create_connection((parsed.hostname, port), timeout=3).close()
    except OSError as error:
        raise EvaluationError(f"no Dask scheduler answers at {address} ({error.strerror or error}); start one "
                              "(dask scheduler) or drop --dask") from None


def image_digest(shot) -> str:
    """SHA-256 of a shot's image file: a cached posterior answers for these bytes only."""
    return file_digest(shot.file)


def _cached(path: Path, digest: str | None = None) -> bool:
    """Whether a posterior is cached and readable, and made from the image as it is now (``digest``,
    when the cache recorded one). An unreadable file (a disk that filled up, a copy cut short) is kept
    aside as NAME.corrupt, a posterior of an image since replaced as NAME.stale, and the posterior is
    sampled again. Caches from before the digest was kept are trusted."""
    if not path.exists():
        return False
    try:
        with np.load(path) as f:
            f["sample_class"], f["seconds"]
            recorded = str(f["image_digest"]) if "image_digest" in f.files else None
    except Exception:                      # numpy and zipfile raise many types for a damaged file
        os.replace(path, path.with_suffix(".corrupt"))
        return False
    if digest is not None and recorded is not None and recorded != digest:
        os.replace(path, path.with_suffix(".stale"))
        return False
    return True


def compute_posteriors(dataset: Dataset, model_dir: Path, run_dir: Path, config: EvaluationConfig,
                       progress: Callable[[int, int], None] | None = None,
                       shots: list[int] | None = None) -> None:
    """Sample every missing test posterior (or those of ``shots``, indices into ``dataset.shots``)
    in ``config.jobs`` worker processes (:func:`in_workers`), or on Dask when ``config.dask`` is set."""
    tests = dataset.split("test") if shots is None else [dataset.shots[i] for i in shots]
    digests = {shot.index: image_digest(shot) for shot in tests}
    todo = [(shot.index, likelihood) for likelihood in config.likelihoods for shot in tests
            if not _cached(posterior_path(run_dir, likelihood, shot.index), digests[shot.index])]
    total = len(tests) * len(config.likelihoods)
    done = total - len(todo)
    if progress:
        progress(done, total)
    if not todo:
        return
    threads = None if config.dask else worker_threads(config.jobs)
    calls = [(str(dataset.root), str(model_dir), index, likelihood, config,
              str(posterior_path(run_dir, likelihood, index)), threads) for index, likelihood in todo]
    if config.dask:
        finished = _on_dask(config.dask, posterior_job, calls)
    elif config.jobs > 1:
        finished = in_workers(posterior_job, calls, config.jobs)
    else:
        finished = (posterior_job(*call) for call in calls)
    for _ in finished:
        done += 1
        if progress:
            progress(done, total)


def _on_dask(address: str, function: Callable, calls: list[tuple]):
    """Yield ``function(*call)`` for each of ``calls``, as they finish, computed on the Dask cluster
    whose scheduler is at ``address`` (joblib's Dask backend)."""
    from dask.distributed import Client
    from joblib import Parallel, delayed, parallel_config

    with Client(address), parallel_config(backend="dask"):
        yield from Parallel(n_jobs=None, return_as="generator_unordered")(delayed(function)(*call) for call in calls)


def in_workers(function: Callable, calls: list[tuple], workers: int):
    """Yield ``function(*call)`` for each of ``calls``, as they finish, computed by ``workers`` processes
    that live for the whole run; an error in one call stops the others and is raised here.

    Not joblib's loky executor: it replaces a worker whose memory grew by 300 MB after its first job,
    and a posterior worker's grows that much as JAX compiles the programs of the hypotheses and rounds
    its first image did not need, so each replacement compiled everything again (in the first 20
    posteriors of fsclvr's test split, 4 took 112-159 s against 36-57 s for the rest). Spawned, not
    forked: the parent may already run JAX's and Dr.Jit's threads, which a fork does not copy."""
    import multiprocessing
    from concurrent.futures import ProcessPoolExecutor, as_completed

    executor = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("spawn"))
    try:
        futures = [executor.submit(function, *call) for call in calls]
        for future in as_completed(futures):
            yield future.result()
    except BaseException:          # an error, Ctrl-C or an abandoned generator: no worker may keep computing
        for process in list((getattr(executor, "_processes", None) or {}).values()):  # public only from 3.14
            process.terminate()
        raise
    finally:
        executor.shutdown(wait=True, cancel_futures=True)
