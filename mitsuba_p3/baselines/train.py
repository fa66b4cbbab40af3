"""Meta-training and evaluation of the baselines on a benchmark (resumable, with checkpoints).

``train_baseline`` meta-trains on episodes drawn from the data set's *train*
classes: Adam 1e-3 (optax), ``meta_batch`` tasks per iteration, each task N-way
K-shot with the rest of every class's shots as queries. The N-way of each task
alternates between ``train_ways`` (5 and 10 by default, the two test settings;
ways above the number of training classes are skipped).
Every ``checkpoint_every`` iterations the parameters, the optimiser state, the
RNG and the learning curve go to ``DIR`` (a rerun resumes from them, and refuses
a folder trained with other settings):

==========================  =====================================================
``checkpoint.json``         settings, iteration, RNG state, curves, the name and
                            SHA-256 of the arrays file; written last, so it always
                            names a complete arrays file
``checkpoint-NNNNNN.npz``   parameters, optimiser state and kept parameters, one
                            array per leaf, named by its path in the pytree
==========================  =====================================================

**No pickle.** A checkpoint is data a person can share, so loading one must not
run code: the arrays are read with ``allow_pickle=False`` and put back into the
pytree shapes that the settings' network and optimiser define (a missing or
misshapen leaf is refused). A ``checkpoint.pkl`` of an older mitsuba-p3 is
refused in one line; ``mitsuba-p3 baseline convert DIR`` converts one the user
trusts.

**Early stopping.** ``validation_classes`` of the train classes (a fixed, seeded
choice; at most a third of them) are held out of meta-training. At every checkpoint the network is scored
on the same ``validation_episodes`` episodes of those classes (N-way K-shot over
the test settings they allow, every remaining shot a query); the best parameters
so far are kept, and training stops once ``patience`` checkpoints in a row have
not improved on the best, or at the ``iterations`` cap. Evaluation uses the best
parameters. So a baseline trains until it stops improving on classes it has not
seen, not for a budget-sized count (``validation_classes=0`` restores that).

``evaluate_baseline`` scores the *same* test episodes as P3/NP3
(:func:`mitsuba_p3.benchmarks.episodes.sample_episodes`, seed 0, one query per
class) and writes ``RUN/baselines/NAME.json`` for the evaluation tables.

Images are the data set's, squashed to ``resolution`` x ``resolution`` (the
benchmarks are 4:3; cropping would cut off objects near the sides).
"""
from __future__ import annotations

import hashlib
import io
import json
from dataclasses import asdict, dataclass, field
from functools import partial
from pathlib import Path
from typing import Callable

import numpy as np

from ..errors import BaselineError, check_counts, check_positive
from ..files import atomic_json, atomic_write
from .methods import MAML, METHODS

CHECKPOINT_FORMAT = "mitsuba-p3-baseline"
CHECKPOINT_VERSION = 2          # 1 was a pickle
CHECKPOINT_FILE = "checkpoint.json"
LEGACY_FILE = "checkpoint.pkl"
# Caps only: training stops earlier once the validation accuracy stops improving (the paper used 60K).
DEFAULT_ITERATIONS = {"protonets": 20000, "maml": 20000}



@dataclass(frozen=True)
class TrainConfig:
    method: str = "protonets"
    resolution: int = 56
    iterations: int = 2000
    k_shot: int = 1
    train_ways: tuple = (5, 10)
    meta_batch: int = 2
    learning_rate: float = 1e-3
    second_order: bool = False      # MAML only
    checkpoint_every: int = 100     # and a validation
    validation_classes: int = 10    # train classes held out for early stopping (0: none, train to the cap)
    validation_episodes: int = 40   # fixed validation episodes, over the test settings the classes allow
    patience: int = 10              # checkpoints without a better validation accuracy before stopping
    seed: int = 0

    def __post_init__(self):
        if self.method not in METHODS:
            raise BaselineError(f"unknown baseline {self.method!r}; choose protonets or maml")
        if self.resolution < 16:
            raise BaselineError("the Conv-4 backbone needs images of at least 16x16")
        object.__setattr__(self, "train_ways", tuple(self.train_ways))
        check_counts(self, {"iterations": 1, "k_shot": 1, "meta_batch": 1, "checkpoint_every": 1, "seed": 0,
                            "validation_classes": 0, "validation_episodes": 1, "patience": 1}, "baseline ")
        if self.validation_classes == 1:
            raise BaselineError("early stopping needs at least 2 validation classes (or 0: none)")
        check_positive(self, ("learning_rate",), "baseline ")
        if not self.train_ways or min(self.train_ways) < 2:
            raise BaselineError(f"training ways must be 2 or more; got {self.train_ways}")

    def model(self):
        if self.method == "maml":
            return MAML(second_order=self.second_order)
        return METHODS[self.method]()

    @property
    def label(self) -> str:
        names = {"protonets": "ProtoNets", "maml": "MAML"}
        return f"{names[self.method]} {self.resolution}"


def class_images(dataset, split: str, resolution: int) -> dict[str, np.ndarray]:
    """Each class's shots as (shots, R, R, 3) float32 in [0, 1]."""
    from PIL import Image

    out = {}
    for name in dataset.classes(split):
        shots = []
        for shot in dataset.shots_of(name):
            image = Image.open(shot.file).convert("RGB").resize((resolution, resolution), Image.BOX)
            shots.append(np.asarray(image, np.float32) / 255.0)
        out[name] = np.stack(shots)
    return out


def sample_task(rng: np.random.Generator, images: dict[str, np.ndarray], n_way: int, k_shot: int):
    """An N-way K-shot task from ``images``; every remaining shot of a class is a query."""
    names = sorted(images)
    if n_way > len(names):
        raise BaselineError(f"{n_way}-way tasks need {n_way} classes; the split has {len(names)}")
    fewest = min(len(v) for v in images.values())
    if k_shot >= fewest:
        raise BaselineError(f"{k_shot}-shot tasks need more than {k_shot} shots per class; some class has {fewest}")
    support, labels, queries, query_labels = [], [], [], []
    for label, index in enumerate(rng.choice(len(names), n_way, replace=False)):
        shots = images[names[index]][rng.permutation(len(images[names[index]]))]
        support.append(shots[:k_shot])
        queries.append(shots[k_shot:fewest])
        labels += [label] * k_shot
        query_labels += [label] * (fewest - k_shot)
    return (np.concatenate(support), np.array(labels), np.concatenate(queries), np.array(query_labels), n_way)


@dataclass
class Checkpoint:
    config: dict
    iteration: int
    params: object
    opt_state: object
    rng_state: dict
    curve: list = field(default_factory=list)   # (iteration, loss, accuracy) per iteration
    validation: list = field(default_factory=list)   # (iteration, validation accuracy) per checkpoint
    best_params: object = None                  # the parameters of the best validation accuracy
    best_iteration: int = 0
    stopped: bool = False                       # early-stopped (no improvement for ``patience`` checkpoints)

    @property
    def final_params(self):
        """The parameters to evaluate: the best on validation when there was a validation."""
        return self.params if self.best_params is None else self.best_params

    @property
    def kept_iteration(self) -> int:
        """The iteration of :attr:`final_params` (kept parameters exist once there was a validation)."""
        return self.best_iteration if self.validation else self.iteration

    @property
    def best_validation(self) -> float | None:
        """The best validation accuracy so far (None: no validation)."""
        return max((v[1] for v in self.validation), default=None)

    @classmethod
    def load(cls, folder: Path, arrays: bool = True) -> "Checkpoint":
        """Read ``folder``'s checkpoint; ``arrays=False`` reads only its JSON (the parameters are None),
        all that a status table needs."""
        folder = Path(folder)
        path = folder / CHECKPOINT_FILE
        if not path.is_file():
            if (folder / LEGACY_FILE).is_file():
                raise BaselineError(f"{folder / LEGACY_FILE} is an older pickle checkpoint, which can run code when "
                                    f"read; it is not loaded. If you trust it, convert it: "
                                    f"mitsuba-p3 baseline convert {folder}")
            raise BaselineError(f"{folder} holds no trained baseline (no {CHECKPOINT_FILE})")
        try:
            record = json.loads(path.read_text())
        except (OSError, UnicodeDecodeError, json.JSONDecodeError) as error:
            raise BaselineError(f"{path} is not readable JSON ({error}); train again into a new folder") from None
        if not isinstance(record, dict) or record.get("format") != CHECKPOINT_FORMAT:
            raise BaselineError(f"{path} is not a mitsuba-p3 baseline checkpoint")
        fields = {k: record.get(k) for k in ("config", "iteration", "rng_state", "best_iteration", "stopped")}
        try:
            fields["config"] = asdict(TrainConfig(**fields["config"]))   # tuples again, settings checked
        except TypeError as error:
            raise BaselineError(f"{path}: its settings are not a baseline's ({error})") from None
        state = cls(**fields, params=None, opt_state=None, curve=[tuple(c) for c in record.get("curve", [])],
                    validation=[tuple(v) for v in record.get("validation", [])])
        if arrays:
            state._read_arrays(folder, record)
        return state

    def _read_arrays(self, folder: Path, record: dict) -> None:
        """Fill params, opt_state and best_params from the arrays file the JSON names, checked against
        its digest and against the pytree shapes of the settings' network and optimiser."""
        name = str(record.get("arrays", ""))
        path = folder / name
        if "/" in name or "\\" in name or not name.endswith(".npz") or not path.is_file():
            raise BaselineError(f"{folder}: the arrays file {name!r} named by {CHECKPOINT_FILE} is missing")
        data = path.read_bytes()
        if hashlib.sha256(data).hexdigest() != record.get("arrays_sha256"):
            raise BaselineError(f"{path} does not match the digest in {CHECKPOINT_FILE}: damaged or replaced")
        try:
            with np.load(io.BytesIO(data), allow_pickle=False) as stored:
                leaves = {key: stored[key] for key in stored.files}
        except (ValueError, OSError) as error:
            raise BaselineError(f"{path} is not a plain array file ({error})") from None
        params, opt_state = checkpoint_templates(TrainConfig(**self.config))
        self.params = _fill(params, leaves, "params", path)
        self.opt_state = _fill(opt_state, leaves, "opt_state", path)
        self.best_params = _fill(params, leaves, "best_params", path) if record.get("has_best") else None

    def save(self, folder: Path) -> None:
        """Write the arrays file, then the JSON that names it (atomic each), then remove older arrays files."""
        folder = Path(folder)
        leaves = {**_leaves(self.params, "params"), **_leaves(self.opt_state, "opt_state")}
        if self.best_params is not None:
            leaves.update(_leaves(self.best_params, "best_params"))
        buffer = io.BytesIO()
        np.savez(buffer, **leaves)
        name = f"checkpoint-{self.iteration:06d}.npz"
        atomic_write(folder / name, buffer.getvalue())
        record = {"format": CHECKPOINT_FORMAT, "version": CHECKPOINT_VERSION, "config": self.config,
                  "iteration": self.iteration, "rng_state": self.rng_state, "best_iteration": self.best_iteration,
                  "stopped": self.stopped, "arrays": name, "has_best": self.best_params is not None,
                  "arrays_sha256": hashlib.sha256(buffer.getvalue()).hexdigest(),
                  "curve": [list(c) for c in self.curve], "validation": [list(v) for v in self.validation]}
        atomic_write(folder / CHECKPOINT_FILE, json.dumps(record, separators=(",", ":")))
        for old in folder.glob("checkpoint-*.npz"):
            if old.name != name:
                old.unlink()


def checkpoint_templates(config: TrainConfig):
    """The pytree shapes (jax.ShapeDtypeStruct leaves) of ``config``'s parameters and optimiser state:
    what a checkpoint's arrays are read into. Nothing is computed (``jax.eval_shape``)."""
    import jax
    import optax

    model = config.model()
    params = jax.eval_shape(lambda: model.init(jax.random.PRNGKey(config.seed), config.resolution))
    return params, jax.eval_shape(optax.adam(config.learning_rate).init, params)


def _leaves(tree, prefix: str) -> dict[str, np.ndarray]:
    import jax

    return {prefix + jax.tree_util.keystr(path): np.asarray(leaf)
            for path, leaf in jax.tree_util.tree_flatten_with_path(tree)[0]}


def _fill(template, leaves: dict, prefix: str, path: Path):
    """``template``'s pytree with each leaf read from ``leaves`` by its path, shape and dtype checked."""
    import jax

    paths, treedef = jax.tree_util.tree_flatten_with_path(template)
    values = []
    for key_path, leaf in paths:
        key = prefix + jax.tree_util.keystr(key_path)
        value = leaves.get(key)
        if value is None or value.shape != tuple(leaf.shape):
            found = "missing" if value is None else f"shape {value.shape}"
            raise BaselineError(f"{path}: {key} is {found}, the network needs {tuple(leaf.shape)}; "
                                "the checkpoint is incomplete or from another network")
        values.append(np.asarray(value, leaf.dtype))
    return jax.tree_util.tree_unflatten(treedef, values)


def has_checkpoint(folder: Path) -> bool:
    """Whether ``folder`` is a training folder (a checkpoint, or an older pickle one to convert)."""
    return (Path(folder) / CHECKPOINT_FILE).is_file() or (Path(folder) / LEGACY_FILE).is_file()


def convert_legacy_checkpoint(folder: Path) -> Path:
    """Convert a trusted ``checkpoint.pkl`` of an older mitsuba-p3 into today's files, check that they
    read back to the same arrays, and remove the pickle. **Unpickling runs code**: only for files the
    user trusts (``mitsuba-p3 baseline convert`` says so)."""
    import pickle

    folder = Path(folder)
    legacy = folder / LEGACY_FILE
    if not legacy.is_file():
        raise BaselineError(f"{folder} holds no {LEGACY_FILE} to convert")
    with open(legacy, "rb") as f:
        record = pickle.load(f)   # noqa: S301 - the user vouched for this file (see the docstring)
    if not isinstance(record, dict) or record.get("format") != CHECKPOINT_FORMAT:
        raise BaselineError(f"{legacy} is not a mitsuba-p3 baseline checkpoint")
    state = Checkpoint(**{k: v for k, v in record.items() if k != "format"})
    state.save(folder)
    back = Checkpoint.load(folder)
    for name in ("params", "opt_state", "best_params"):
        before, after = _leaves(getattr(state, name), name), _leaves(getattr(back, name), name)
        if before.keys() != after.keys() or any(not np.array_equal(before[k], after[k]) for k in before):
            raise BaselineError(f"{folder}: the converted {name} do not read back equal; the pickle is kept")
    legacy.unlink()
    return folder / CHECKPOINT_FILE


def train_baseline(dataset_dir: str | Path, out: str | Path, config: TrainConfig,
                   progress: Callable[[int, int], None] | None = None) -> Checkpoint:
    """Meta-train (or resume) a baseline on a benchmark's train split; writes the learning curve."""
    from ..benchmarks.dataset import load_dataset

    images = class_images(load_dataset(dataset_dir), "train", config.resolution)
    return meta_train(images, out, config, progress)


def split_validation(images: dict[str, np.ndarray], count: int, seed: int) -> tuple[dict, dict]:
    """(training, validation) classes: ``count`` classes held out by a seeded draw, at most a third
    of them; none when that leaves fewer than 2 (a tiny benchmark trains to its cap)."""
    names = sorted(images)
    count = min(count, len(names) // 3)
    count = count if count >= 2 else 0
    held = set(np.random.default_rng(seed).choice(len(names), count, replace=False).tolist()) if count else set()
    return ({n: images[n] for i, n in enumerate(names) if i not in held},
            {n: images[n] for i, n in enumerate(names) if i in held})


def validation_tasks(images: dict[str, np.ndarray], episodes: int, seed: int) -> list:
    """Fixed validation episodes over the N-way K-shot test settings the held-out classes allow."""
    from ..evaluate.metrics import feasible_settings

    if not images:
        return []
    settings = feasible_settings(len(images), min(len(v) for v in images.values()) - 1)
    rng = np.random.default_rng(seed + 1)
    return [sample_task(rng, images, *settings[e % len(settings)]) for e in range(episodes)]


def validation_accuracy(predict, params, tasks: list) -> float:
    """Mean query accuracy over the validation episodes."""
    return float(np.mean([episode_accuracy(predict, params, support, len(labels) // n_way, queries, truth, n_way)
                          for support, labels, queries, truth, n_way in tasks]))


def meta_train(images: dict[str, np.ndarray], out: str | Path, config: TrainConfig,
               progress: Callable[[int, int], None] | None = None) -> Checkpoint:
    """Meta-train (or resume) on ``images`` (class -> (shots, R, R, 3)), holding out
    ``config.validation_classes`` for early stopping; returns the final checkpoint."""
    import jax
    import optax

    images, held_out = split_validation(images, config.validation_classes, config.seed)
    tasks = validation_tasks(held_out, config.validation_episodes, config.seed)
    out = Path(out)
    from ..files import refuse_protected_folder

    refuse_protected_folder(out, "mitsuba-p3 baseline train")
    out.mkdir(parents=True, exist_ok=True)
    model = config.model()
    optimiser = optax.adam(config.learning_rate)
    settings = asdict(config)
    if has_checkpoint(out):
        state = Checkpoint.load(out)
        changed = [k for k in settings if k not in ("iterations", "patience") and state.config.get(k) != settings[k]]
        if changed:
            raise BaselineError(f"{out} holds a baseline trained with other settings ({', '.join(changed)})")
        state.config = settings
    else:
        params = model.init(jax.random.PRNGKey(config.seed), config.resolution)
        state = Checkpoint(settings, 0, params, optimiser.init(params),
                           np.random.default_rng(config.seed).bit_generator.state)
    rng = np.random.default_rng()
    rng.bit_generator.state = state.rng_state

    @partial(jax.jit, static_argnums=3)
    def update(params, opt_state, tasks, way):
        def loss(p):
            values = [model.task_loss(p, (*task, way)) for task in tasks]
            return sum(v[0] for v in values) / len(values), sum(v[1] for v in values) / len(values)

        (value, accuracy), grads = jax.value_and_grad(loss, has_aux=True)(params)
        updates, opt_state = optimiser.update(grads, opt_state, params)
        return optax.apply_updates(params, updates), opt_state, value, accuracy

    ways = [w for w in config.train_ways if w <= len(images)]
    if not ways:
        raise BaselineError(f"the training split has {len(images)} classes: too few for {config.train_ways}-way tasks")
    predict = jax.jit(model.predict, static_argnums=4)
    params, opt_state = state.params, state.opt_state
    # resumed with another patience: whether training has stopped is decided again
    state.stopped = bool(tasks) and since_best(state) >= config.patience
    while state.iteration < config.iterations and not state.stopped:
        way = ways[state.iteration % len(ways)]
        batch = tuple(sample_task(rng, images, way, config.k_shot)[:4] for _ in range(config.meta_batch))
        params, opt_state, value, accuracy = update(params, opt_state, batch, way)
        state.iteration += 1
        state.curve.append((state.iteration, float(value), float(accuracy)))
        if state.iteration % config.checkpoint_every == 0 or state.iteration == config.iterations:
            state.params, state.opt_state, state.rng_state = params, opt_state, rng.bit_generator.state
            if tasks:
                score = validation_accuracy(predict, params, tasks)
                state.validation.append((state.iteration, score))
                if since_best(state) == 0:
                    state.best_params, state.best_iteration = params, state.iteration
                state.stopped = since_best(state) >= config.patience
            state.save(out)
        if progress:
            progress(state.iteration, config.iterations)
    state.params, state.opt_state = params, opt_state
    learning_curve(out, state.curve, config.label, state.validation, state.best_iteration)
    return state


def since_best(state: Checkpoint) -> int:
    """Checkpoints since the best validation accuracy (ties: the earliest); 0 when there is none yet."""
    if not state.validation:
        return 0
    return len(state.validation) - 1 - int(np.argmax([v[1] for v in state.validation]))


def learning_curve(out: Path, curve: list, label: str, validation: list = (), best: int = 0) -> Path:
    """``curve.csv``, ``validation.csv`` and ``learning_curve.png`` (meta-training loss and query
    accuracy, smoothed, with the validation accuracy per checkpoint and the kept one marked)."""
    import matplotlib.pyplot as plt

    from ..plots import save_figure

    values = np.asarray(curve, np.float64).reshape(-1, 3)
    np.savetxt(out / "curve.csv", values, delimiter=",", header="iteration,loss,accuracy", comments="")
    figure, axes = plt.subplots(1, 2, figsize=(8, 3))
    window = max(1, len(values) // 50)
    smooth = lambda v: np.convolve(v, np.ones(window) / window, mode="valid")  # noqa: E731
    for ax, column, name in ((axes[0], 1, "loss"), (axes[1], 2, "query accuracy")):
        ax.plot(values[:, 0], values[:, column], color="0.8", lw=0.5)
        ax.plot(values[window - 1:, 0], smooth(values[:, column]), lw=1.5)
        ax.set_xlabel("iteration")
        ax.set_title(f"{label}: meta-training {name}")
    if len(validation):
        checked = np.asarray(validation, np.float64).reshape(-1, 2)
        np.savetxt(out / "validation.csv", checked, delimiter=",", header="iteration,accuracy", comments="")
        axes[1].plot(checked[:, 0], checked[:, 1], "o-", ms=3, color="C1", label="validation classes")
        axes[1].axvline(best, color="C1", ls=":", label=f"kept: iteration {best}")
        axes[1].legend(fontsize=7, loc="lower right")
    axes[0].set_yscale("log")
    return save_figure(figure, out / "learning_curve.png")


def score_file(run_dir: str | Path, config: TrainConfig) -> Path:
    """Where a baseline's test score goes in an evaluation run folder (the accuracy tables read it)."""
    return Path(run_dir) / "baselines" / f"{config.method}-{config.resolution}.json"


def scored_benchmarks(benchmark: str) -> list[str]:
    """The benchmarks a network trained on ``benchmark`` is scored on: its own, and ood for fsclvr's
    (ood has no train classes of its own; the paper scores fsclvr's networks there)."""
    return [benchmark] + (["ood"] if benchmark == "fsclvr" else [])


def episode_accuracy(predict, params, support, k_shot: int, queries, truth, n_way: int) -> float:
    """Query accuracy of one episode (support ordered class by class, K shots each)."""
    probabilities = np.asarray(predict(params, support, np.repeat(np.arange(n_way), k_shot), queries, n_way))
    return float(np.mean(np.argmax(probabilities, axis=1) == truth))


def evaluate_baseline(model_dir: str | Path, dataset_dir: str | Path, run_dir: str | Path, episodes: int = 100,
                      seed: int = 0, progress: Callable[[int, int], None] | None = None) -> dict:
    """Accuracy (95% interval over episodes) on the shared test episodes; writes RUN/baselines/NAME.json."""
    import jax

    from ..benchmarks.dataset import load_dataset
    from ..benchmarks.episodes import sample_episodes
    from ..evaluate.metrics import feasible_settings, interval95, setting_name

    from ..files import refuse_protected_folder

    refuse_protected_folder(run_dir, "mitsuba-p3 baseline evaluate")
    state = Checkpoint.load(model_dir)
    config = TrainConfig(**state.config)
    model = config.model()
    dataset = load_dataset(dataset_dir)
    images = class_images(dataset, "test", config.resolution)
    by_index = {shot.index: images[shot.class_name][n] for name in dataset.classes("test")
                for n, shot in enumerate(dataset.shots_of(name))}
    fewest = min(len(v) for v in images.values())
    settings = feasible_settings(len(images), fewest)
    predict = jax.jit(model.predict, static_argnums=4)
    accuracy, done = {}, 0
    for n_way, k_shot in settings:
        scores = []
        for episode in sample_episodes(dataset, n_way, k_shot, episodes, seed, queries_per_class=1):
            support = np.stack([by_index[i] for shots in episode.support for i in shots])
            queries = np.stack([by_index[i] for i, _ in episode.queries])
            truth = np.array([t for _, t in episode.queries])
            scores.append(episode_accuracy(predict, state.final_params, support, k_shot, queries, truth, n_way))
            done += 1
            if progress:
                progress(done, episodes * len(settings))
        mean, half = interval95(scores)
        accuracy[setting_name(n_way, k_shot)] = {"mean": mean, "half_width": half, "episodes": episodes}
    result = {"model": config.label, "trained": state.config, "iterations": state.iteration,
              "kept_iteration": state.kept_iteration,
              "early_stopped": state.stopped, "accuracy": accuracy}
    atomic_json(score_file(run_dir, config), result)
    return result


def train_all(data: str | Path, out: str | Path, benchmarks=("fsclvr", "dark", "room"), methods=("protonets", "maml"),
              resolutions=(56, 84), episodes: int = 100, patience: int | None = None, iterations: int | None = None,
              rescore: bool = False, progress_bar=None):
    """Every baseline of the paper's table, trained to early stopping and scored, resumable; yields one
    record per finished baseline (iterations, kept iteration, best validation accuracy, test accuracy
    per benchmark it is scored on).

    For each benchmark, method and input size: meta-train on the benchmark's train classes
    (checkpoints in ``out/baselines/V-METHOD-R``), then score the kept network on the test episodes of
    the benchmark (and of ood for fsclvr's networks: :func:`scored_benchmarks`) into ``out/runs/T``, the
    run folders of ``mitsuba-p3 reproduce``. A finished training is not repeated, an unfinished one
    continues from its checkpoint, and a score is kept unless ``rescore`` or the kept network changed.
    ``progress_bar(name) -> (context, update)`` shows each training and scoring."""
    data, out = Path(data), Path(out)
    missing = [b for b in benchmarks if not (data / b / "labels.json").is_file()]
    if missing:
        raise BaselineError(f"no benchmark folder for {', '.join(missing)} in {data} "
                            f"(mitsuba-p3 benchmark generate V --out {data}/V)")
    from contextlib import nullcontext

    bar_of = progress_bar or (lambda name: (nullcontext(), None))
    for benchmark in benchmarks:
        for method in methods:
            for resolution in resolutions:
                name = f"{benchmark}-{method}-{resolution}"
                trained = out / "baselines" / name
                config = TrainConfig(method=method, resolution=int(resolution),
                                     iterations=iterations or DEFAULT_ITERATIONS[method],
                                     **({"patience": patience} if patience is not None else {}))
                bar, update = bar_of(name)
                with bar:
                    state = train_baseline(data / benchmark, trained, config, progress=update)
                scored = {}
                for target in [t for t in scored_benchmarks(benchmark) if (data / t).is_dir()]:
                    result_file = score_file(out / "runs" / target, config)
                    if rescore or not result_file.exists() or _scored_before(result_file, state):
                        bar, update = bar_of(f"{name}: scoring on {target}")
                        with bar:
                            evaluate_baseline(trained, data / target, out / "runs" / target, episodes, progress=update)
                    result = json.loads(result_file.read_text())
                    scored[target] = {k: round(100 * v["mean"], 1) for k, v in result["accuracy"].items()}
                    if target == benchmark:     # the training folder keeps its own score (baseline status reads it)
                        atomic_json(trained / "scores.json", result)
                yield {"baseline": name, "iterations": state.iteration, "early_stopped": state.stopped,
                       "kept_iteration": state.kept_iteration, "best_validation_accuracy": state.best_validation,
                       "test_accuracy": scored}


def _scored_before(result_file: Path, state: Checkpoint) -> bool:
    """A score written for an earlier checkpoint than the one training has kept since."""
    return json.loads(result_file.read_text()).get("kept_iteration") != state.kept_iteration

