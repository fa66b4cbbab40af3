"""Why ProtoNets at 84 px does worse than at 56: the flattened embedding keeps where the object is.

The paper's Conv-4 flattens its last feature map: 3x3x64 at 56 px, 5x5x64 at 84 px. The
benchmarks' objects sit anywhere within +-8 cm of the centre, so a finer map tells more about
*where* an object is and a squared distance between flattened embeddings weighs position beside
appearance. This probe scores, on a benchmark's validation classes (the train classes that
early stopping holds out; the same fixed episodes), untrained networks (three seeds) with the
flattened embedding and with a global average pool over the last map (which forgets where in the
map a feature was), and the kept network of each ProtoNets training found in ``--baselines``. A second table asks
the question directly: between two images of one validation class (same look, different place),
how well the distance of their embeddings follows the distance of the objects on the floor
(Spearman's rank correlation over a class's pairs, averaged over classes; 0 for an embedding
that ignores where the object stands). Train classes only.

    python experiments/probe_baseline_pooling.py data-lo --baselines results/baselines-lo --benchmarks fsclvr,room
"""
from __future__ import annotations

import argparse
from pathlib import Path

import jax
import jax.numpy as jnp
import numpy as np
from scipy.stats import spearmanr

from mitsuba_p3.baselines import conv4
from mitsuba_p3.baselines.methods import ProtoNets
from mitsuba_p3.baselines.train import (Checkpoint, TrainConfig, has_checkpoint, class_images, split_validation,
                                        validation_accuracy, validation_tasks)
from mitsuba_p3.benchmarks.dataset import load_dataset


class PooledProtoNets(ProtoNets):
    """ProtoNets on the last feature map's average over positions (64 numbers at any resolution)."""

    def embed(self, params, images):
        return conv4.feature_map(params["backbone"], images).mean(axis=(1, 2))


def place_correlation(embed, params, held: dict, positions: dict) -> float:
    """Mean over classes of the rank correlation, over pairs of one class's shots, between the
    embeddings' distance and the objects' distance on the floor (x, y)."""
    names = sorted(held)
    # BatchNorm normalises with its batch's statistics: every held-out image in one batch, as in an
    # episode of many classes (one class alone would normalise its shared look away)
    embedded = np.asarray(embed(params, jnp.asarray(np.concatenate([held[n] for n in names]))))
    values, start = [], 0
    for name in names:
        e, place = embedded[start:start + len(held[name])], positions[name]
        start += len(held[name])
        pairs = [(i, j) for i in range(len(e)) for j in range(i + 1, len(e))]
        values.append(spearmanr([np.linalg.norm(e[i] - e[j]) for i, j in pairs],
                                [np.linalg.norm(place[i][:2] - place[j][:2]) for i, j in pairs]).statistic)
    return float(np.mean(values))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("data", type=Path, help="folder with one benchmark folder per name")
    parser.add_argument("--baselines", type=Path, default=Path("results/baselines-lo"))
    parser.add_argument("--benchmarks", default="fsclvr,room,dark")
    parser.add_argument("--seeds", type=int, default=3)
    args = parser.parse_args()
    defaults = TrainConfig()
    flattened, pooled = ProtoNets(), PooledProtoNets()
    # compiled once, for every benchmark (one compilation per input shape)
    compiled = {model: (jax.jit(model.predict, static_argnums=4), jax.jit(model.embed)) for model in (flattened, pooled)}
    accuracy, place = [], []
    for benchmark in args.benchmarks.split(","):
        dataset = load_dataset(args.data / benchmark)
        for resolution in (56, 84):
            images = class_images(dataset, "train", resolution)
            _, held = split_validation(images, defaults.validation_classes, defaults.seed)
            positions = {name: [shot.position for shot in dataset.shots_of(name)] for name in held}
            tasks = validation_tasks(held, defaults.validation_episodes, defaults.seed)
            scores, correlations = [], []
            for model, (predict, embed) in compiled.items():
                inits = [model.init(jax.random.PRNGKey(s), resolution) for s in range(args.seeds)]
                values = [validation_accuracy(predict, params, tasks) for params in inits]
                scores.append(f"{np.mean(values):.3f} ({min(values):.3f}-{max(values):.3f})")
                correlations.append(f"{np.mean([place_correlation(embed, p, held, positions) for p in inits]):+.2f}")
            folder = args.baselines / f"{benchmark}-protonets-{resolution}"
            if has_checkpoint(folder):
                state = Checkpoint.load(folder)
                predict, embed = compiled[flattened]
                scores.append(f"{validation_accuracy(predict, state.final_params, tasks):.3f} "
                              f"(iteration {state.kept_iteration})")
                correlations.append(f"{place_correlation(embed, state.final_params, held, positions):+.2f}")
            else:
                scores.append("not trained")
                correlations.append("not trained")
            accuracy.append(f"| {benchmark} | {resolution} | " + " | ".join(scores) + " |")
            place.append(f"| {benchmark} | {resolution} | " + " | ".join(correlations) + " |")
    header = "| benchmark | px | untrained, flattened | untrained, pooled | trained (kept), flattened |\n|---|---|---|---|---|"
    print("Validation accuracy (held-out train classes):\n\n" + header + "\n" + "\n".join(accuracy))
    print("\nRank correlation of embedding distance with floor distance, within a class:\n\n"
          + header + "\n" + "\n".join(place))


if __name__ == "__main__":
    main()
