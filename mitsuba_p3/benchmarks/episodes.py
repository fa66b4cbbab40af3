"""N-way K-shot episodes over a data set's test classes, seeded and shared by every model.

An episode picks N classes, K support shots of each, and query shots of the
same classes disjoint from the support. P3/NP3 and the baselines evaluate on
the very same episodes because they are a pure function of (data set, N, K,
queries, count, seed).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from .dataset import Dataset
from ..errors import BenchmarkError


@dataclass(frozen=True)
class Episode:
    """Indices into ``Dataset.shots``: ``support[i]`` are class ``classes[i]``'s K shots;
    ``queries`` are (shot index, true class position in ``classes``) pairs."""

    classes: tuple[str, ...]
    support: tuple[tuple[int, ...], ...]
    queries: tuple[tuple[int, int], ...]

    @property
    def n_way(self) -> int:
        return len(self.classes)

    @property
    def k_shot(self) -> int:
        return len(self.support[0])


def sample_episodes(dataset: Dataset, n_way: int, k_shot: int, n_episodes: int, seed: int = 0,
                    queries_per_class: int = 1, split: str = "test") -> list[Episode]:
    """Draw ``n_episodes`` episodes; queries never repeat a support shot of the episode."""
    classes = dataset.classes(split)
    if n_way < 1 or k_shot < 1 or queries_per_class < 1 or n_episodes < 1:
        raise BenchmarkError("n_way, k_shot, queries_per_class and n_episodes must be positive")
    if n_way > len(classes):
        raise BenchmarkError(f"{n_way}-way episodes need {n_way} {split} classes; "
                             f"{dataset.root} has {len(classes)}")
    shots = {name: [s.index for s in dataset.shots_of(name)] for name in classes}
    fewest = min(len(v) for v in shots.values())
    if k_shot + queries_per_class > fewest:
        raise BenchmarkError(f"{k_shot}-shot episodes with {queries_per_class} quer(ies) per class need "
                             f"{k_shot + queries_per_class} shots per class; some {split} class has {fewest}")
    rng = np.random.default_rng([seed, n_way, k_shot, queries_per_class])
    episodes = []
    for _ in range(n_episodes):
        chosen = [classes[i] for i in sorted(rng.choice(len(classes), size=n_way, replace=False))]
        support, queries = [], []
        for position, name in enumerate(chosen):
            order = rng.permutation(shots[name])
            support.append(tuple(int(i) for i in order[:k_shot]))
            queries += [(int(i), position) for i in order[k_shot:k_shot + queries_per_class]]
        episodes.append(Episode(tuple(chosen), tuple(support), tuple(queries)))
    return episodes
