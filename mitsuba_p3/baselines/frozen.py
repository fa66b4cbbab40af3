"""Frozen pretrained features: the few-shot baseline a reviewer asks for first.

A network pretrained on a large data set is not trained further; its features of every
image are classified per episode by

- **nearest centroid** ("SimpleShot", Wang et al. 2019): features centred on the mean
  feature of the train classes' images and L2-normalised ("CL2N"), each class's centroid
  the mean of its support features, a query given to the centroid of highest cosine;
- **a linear probe** (Tian et al. 2020): a logistic regression (scikit-learn, L2 penalty of
  strength 1 / C) fitted on each episode's support features (the same CL2N features).

The network is the ImageNet VGG16 the project already ships for NP3's neural likelihood
(:mod:`mitsuba_p3.fit.features`; nothing downloaded). A layer's feature is its ReLU output
averaged over the map (global average pooling), for square images of ``RESOLUTION`` pixels
made as the other baselines' are (:func:`~mitsuba_p3.baselines.train.class_images`). The layer
(and the probe's C) are chosen on validation episodes of held-out train classes
(:func:`~mitsuba_p3.baselines.train.split_validation`), as the meta-learned baselines' early
stopping is; test scores use the episodes P3 is scored on. ood has no train classes: it takes
fsclvr's choices and centring mean (``choose_on``).
"""
from __future__ import annotations

from dataclasses import asdict, dataclass
from pathlib import Path
from typing import Callable

import numpy as np

# pooled conv outputs tried (the last conv of the three deepest blocks), the probe's inverse
# regularisation strengths tried, and the square image size
LAYERS_TRIED = ("conv3_3", "conv4_3", "conv5_3")
C_TRIED = (0.1, 1.0, 10.0, 100.0)
RESOLUTION = 84
METHODS = ("centroid", "probe")
LABELS = {"centroid": "VGG16 frozen + centroid", "probe": "VGG16 frozen + linear probe"}
BATCH = 32
# a third of the train classes are held out for validation, and a 5-way episode needs 5 of them
MIN_TRAIN_CLASSES = 15


def embed(images: np.ndarray, layer: str) -> np.ndarray:
    """(B, R, R, 3) images in [0, 1] -> (B, C) features: ``layer``'s ReLU output, averaged over the map."""
    import jax
    import jax.numpy as jnp

    from ..fit.features import LAYERS, vgg_features

    depth = LAYERS.index(layer) + 1
    pooled = jax.jit(lambda x: jnp.mean(jax.nn.relu(vgg_features(x, depth)[-1]), axis=(1, 2)))
    return np.concatenate([np.asarray(pooled(images[i:i + BATCH])) for i in range(0, len(images), BATCH)])


def features(images: dict[str, np.ndarray], layer: str) -> dict[str, np.ndarray]:
    """Each class's shots (shots, R, R, 3) as their features (shots, C)."""
    names = sorted(images)
    flat = embed(np.concatenate([images[n] for n in names]), layer)
    splits = np.cumsum([len(images[n]) for n in names])[:-1]
    return dict(zip(names, np.split(flat, splits)))


def normalised(x: np.ndarray, mean: np.ndarray) -> np.ndarray:
    """CL2N: centred on ``mean`` (the train classes' mean feature), then of unit length."""
    centred = x - mean
    return centred / np.maximum(np.linalg.norm(centred, axis=-1, keepdims=True), 1e-12)


def predict_centroid(support: np.ndarray, labels: np.ndarray, queries: np.ndarray, n_way: int) -> np.ndarray:
    """(Q, n_way) cosine similarities of normalised queries to each class's mean normalised support."""
    centroids = np.stack([support[labels == k].mean(axis=0) for k in range(n_way)])
    centroids /= np.maximum(np.linalg.norm(centroids, axis=1, keepdims=True), 1e-12)
    return queries @ centroids.T


def predict_probe(support: np.ndarray, labels: np.ndarray, queries: np.ndarray, n_way: int,
                  c: float) -> np.ndarray:
    """(Q, n_way) class probabilities of a logistic regression fitted on the support set."""
    from sklearn.linear_model import LogisticRegression

    model = LogisticRegression(C=c, max_iter=2000)
    model.fit(support, labels)
    return model.predict_proba(queries)


@dataclass(frozen=True)
class Choice:
    """A frozen baseline's settings: method, layer, the probe's C (None for the centroid), the
    validation accuracy they reached, and where they were chosen."""
    method: str
    layer: str
    c: float | None
    validation_accuracy: float
    chosen_on: str


def _accuracy(method: str, c: float | None, tasks: list, mean: np.ndarray) -> float:
    """Mean query accuracy of a method over feature-space episodes, features centred on ``mean``."""
    scores = []
    for support, labels, queries, truth, n_way in tasks:
        s, q = normalised(support, mean), normalised(queries, mean)
        predicted = predict_centroid(s, labels, q, n_way) if method == "centroid" else \
            predict_probe(s, labels, q, n_way, c)
        scores.append(float(np.mean(np.argmax(predicted, axis=1) == truth)))
    return float(np.mean(scores))


def choose(train: dict[str, np.ndarray], chosen_on: str, validation_classes: int = 10, episodes: int = 100,
           seed: int = 0) -> tuple[dict[str, Choice], dict[str, np.ndarray]]:
    """Per method the layer (and C) with the best accuracy on validation episodes of held-out train
    classes (the same draws for every candidate); returns the choices and each layer's centring mean
    (over all train images; while choosing, over the classes not held out)."""
    from ..evaluate.metrics import feasible_settings
    from .train import split_validation, validation_tasks

    kept, held = split_validation(train, validation_classes, seed)
    if not held or not feasible_settings(len(held), min(len(v) for v in held.values()) - 1):
        from ..errors import BaselineError

        raise BaselineError(f"choosing a frozen baseline's layer needs validation episodes of 5 held-out train "
                            f"classes with 2 or more images each, so at least {MIN_TRAIN_CLASSES} train classes; "
                            f"this one has {len(train)}")
    best: dict[str, Choice] = {}
    means = {}
    for layer in LAYERS_TRIED:
        by_class = features(train, layer)
        means[layer] = np.concatenate(list(by_class.values())).mean(axis=0)
        centre = np.concatenate([by_class[name] for name in kept]).mean(axis=0)   # nothing of the held-out classes
        # the validation episodes drawn over the held-out classes' features: the same draws for every layer
        tasks = validation_tasks({name: by_class[name] for name in held}, episodes, seed)
        for method in METHODS:
            for c in (C_TRIED if method == "probe" else (None,)):
                accuracy = _accuracy(method, c, tasks, centre)
                if method not in best or accuracy > best[method].validation_accuracy:
                    best[method] = Choice(method, layer, c, accuracy, chosen_on)
    return best, means


def score(dataset, choices: dict[str, Choice], means: dict[str, np.ndarray], run_dir: str | Path,
          episodes: int = 100, seed: int = 0, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Accuracy (95% interval over episodes) of each chosen frozen baseline on ``dataset``'s test
    episodes, the ones P3 is scored on; writes RUN/baselines/frozen-METHOD.json (the tables' rows)."""
    from ..benchmarks.episodes import sample_episodes
    from ..evaluate.metrics import feasible_settings, interval95, setting_name
    from ..files import atomic_json, refuse_protected_folder
    from .train import class_images

    refuse_protected_folder(run_dir, "mitsuba-p3 baseline frozen")
    images = class_images(dataset, "test", RESOLUTION)
    settings = feasible_settings(len(images), min(len(v) for v in images.values()))
    by_layer = {}
    results, done, total = [], 0, len(choices) * len(settings) * episodes
    for method, choice in choices.items():
        if choice.layer not in by_layer:
            by_class = features(images, choice.layer)
            by_layer[choice.layer] = {shot.index: normalised(by_class[name][n], means[choice.layer])
                                      for name in dataset.classes("test")
                                      for n, shot in enumerate(dataset.shots_of(name))}
        vectors = by_layer[choice.layer]
        accuracy = {}
        for n_way, k_shot in settings:
            scores = []
            for episode in sample_episodes(dataset, n_way, k_shot, episodes, seed, queries_per_class=1):
                support = np.stack([vectors[i] for shots in episode.support for i in shots])
                labels = np.repeat(np.arange(n_way), k_shot)
                queries = np.stack([vectors[i] for i, _ in episode.queries])
                truth = np.array([t for _, t in episode.queries])
                predicted = predict_centroid(support, labels, queries, n_way) if method == "centroid" else \
                    predict_probe(support, labels, queries, n_way, choice.c)
                scores.append(float(np.mean(np.argmax(predicted, axis=1) == truth)))
                done += 1
                if progress:
                    progress(done, total)
            mean, half = interval95(scores)
            accuracy[setting_name(n_way, k_shot)] = {"mean": mean, "half_width": half, "episodes": episodes}
        result = {"model": LABELS[method], "frozen": {**asdict(choice), "resolution": RESOLUTION}, "accuracy": accuracy}
        atomic_json(Path(run_dir) / "baselines" / f"frozen-{method}.json", result)
        results.append(result)
    return results


def score_benchmark(dataset_dir: str | Path, run_dir: str | Path, choose_on: str | Path | None = None,
                    episodes: int = 100, progress: Callable[[int, int], None] | None = None) -> list[dict]:
    """Choose on ``choose_on``'s train classes (default: the data set's own) and score the data set's
    test episodes: what ``mitsuba-p3 baseline frozen`` and ``reproduce`` run."""
    from ..benchmarks.dataset import load_dataset
    from ..errors import BaselineError
    from .train import class_images

    scored = load_dataset(dataset_dir)
    source = load_dataset(choose_on) if choose_on else scored
    train = class_images(source, "train", RESOLUTION)
    if not train:
        raise BaselineError(f"{source.root} has no train classes to choose on; pass --choose-on with a benchmark "
                            "that has (e.g. fsclvr's for ood)")
    choices, means = choose(train, str(source.root))
    return score(scored, choices, means, run_dir, episodes, progress=progress)
