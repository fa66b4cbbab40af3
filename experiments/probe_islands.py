"""Do a hypothesis's independent runs (islands) agree, and on what? Per image, setting and seed.

For each image (a file, or ``--dataset``'s first train image of each named class), each setting of
``--configs`` (JSON: name -> :class:`~mitsuba_p3.infer.smc.SMCConfig` fields) and each seed, runs
the P3 SMC under the model's fitted noise and prints, per shape hypothesis, every island's log
evidence, the share of its particles on the shiny side of the specular prior's threshold, and the
mean acceptance of the material kind's jump where it ran; then the modal shape. Islands of one
hypothesis that end tens of nats apart found different optima; where they differ in the shiny share
too, the material kind may be a trap (``{"jump": true}`` proposes the other kind whole: if the
evidence does not rise with it, the reading is the likelihood's).

    python experiments/probe_islands.py --model out/model-small \\
        out/fsclvr-small/test/large-cyan-metal-sphere/0.png --seeds 0,1,2,3 \\
        --configs '{"chart": {}, "z": {"chart": false}, "jump": {"jump": true}}'
    python experiments/probe_islands.py --model data/models/fsclvr-lo --dataset data/fsclvr-lo \\
        --classes large-cyan-metal-sphere,large-blue-metal-sphere --configs '{"default": {}, "jump": {"jump": true}}'
"""
from __future__ import annotations

import argparse
import json
import time

import numpy as np

from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.evidence import shape_weights
from mitsuba_p3.infer.hypotheses import hypotheses_of
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.smc import SMCConfig, sample_smc
from mitsuba_p3.shapes import SHAPES
from mitsuba_p3.space import SLICES


def images(args) -> list[tuple[str, np.ndarray, tuple[int, int]]]:
    """(name, image, (height, width)) of every image asked for."""
    out = []
    if args.dataset:
        from mitsuba_p3.benchmarks.dataset import load_dataset

        dataset = load_dataset(args.dataset)
        for name in args.classes.split(","):
            shot = next((s for s in dataset.split("train") if s.class_name == name), None)
            if shot is None:
                raise SystemExit(f"{args.dataset} has no train image of {name}")
            out.append((f"train {name}", dataset.image(shot), dataset.resolution))
    from mitsuba_p3.images import load_observation

    for path in args.images:
        image = load_observation(path)
        out.append((path, image, image.shape[:2]))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("images", nargs="*", help="image files")
    parser.add_argument("--model", required=True)
    parser.add_argument("--dataset", help="with --classes: the first train image of each class")
    parser.add_argument("--classes", default="")
    parser.add_argument("--configs", default='{"default": {}}', help="JSON: name -> SMCConfig fields")
    parser.add_argument("--seeds", default="0")
    args = parser.parse_args()

    fitted = FittedModel(args.model)
    configs = {name: fields for name, fields in json.loads(args.configs).items()}
    spec = SLICES["specular"].start
    cores = {}
    for label, image, size in images(args):
        if size not in cores:
            cores[size] = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise="fitted"), "mitsuba", *size)
        core = cores[size]
        threshold = core.prior.specular_threshold()        # the SMC's own shiny side (its statistics')
        for name, fields in configs.items():
            for seed in (int(s) for s in args.seeds.split(",")):
                config = SMCConfig(**{**fields, "seed": seed})
                start = time.perf_counter()
                run = sample_smc(core, core.observe(image), config)
                rows = run.particles.rows
                space = hypotheses_of(core.prior, config.kinds)
                position = np.asarray(rows.state.position)
                weights = shape_weights(run.statistics)
                jumps = [np.nanmean(np.asarray(s["jump_acceptance"], float)) for s in rows.steps
                         if "jump_acceptance" in s]
                print(f"{label} | {name} seed {seed} | {time.perf_counter() - start:.0f} s | modal "
                      f"{max(weights, key=weights.get)}" + (f" | jump acceptance {np.mean(jumps):.2f}" if jumps else ""))
                for shape in SHAPES:
                    mine = [r for r in range(len(rows.index)) if SHAPES[space.classes[rows.index[r]]] == shape]
                    islands = ", ".join(f"{rows.log_evidence[r]:.1f} (shiny {np.mean(position[r, :, spec] > threshold):.2f})"
                                        for r in mine)
                    print(f"    {shape:9s} p {weights[shape]:.2f}  islands {islands}", flush=True)


if __name__ == "__main__":
    main()
