"""How should the SMC spend its renders? Settings compared on *train* images, side by side in one run.

For evenly spaced train images, runs :func:`~mitsuba_p3.infer.smc.sample_smc` under the
model's fitted Gaussian noise with each setting of ``--configs`` (a JSON object: name ->
:class:`~mitsuba_p3.infer.smc.SMCConfig` fields) and prints, per setting:

- ``shape``: the share of images whose most probable shape hypothesis is the true shape;
- ``log_p_true``: the mean log posterior probability of the true shape (a proper score:
  a confidently wrong answer costs many nats);
- ``mean_log_z_true``: the mean log evidence of the true shape's hypothesis. The evidence
  estimate is biased low when the runs miss the object's pose, so on the same images a
  higher value means a better search;
- ``island_gap``: median and 90th percentile over images of the spread (highest minus lowest)
  of the true shape's runs' log evidence estimates (``islands`` >= 2): the Monte Carlo error of
  one run's evidence, measured within the run. Tempering noise alone (ESS-chosen steps, N
  particles, T temperatures) would give about sqrt(T / N) nats; much more means the runs found
  different poses;
- ``material``: the share of images whose modal shape's run puts most of its particles on
  the right side of the prior's shiny threshold (metal: shiny), a proxy for the learnt rule;
- ``colour``: the share of images whose draws' median chromaticity names the right colour (the
  fit's rule, :class:`~mitsuba_p3.fit.attributes.AttributeRules`), and ``colour_spread``: the
  median over images of the draws' chromaticity standard deviation (mean over r, g, b), how
  wide the colour posterior is (a noise form that forgives a shade can widen it);
- ``seconds``: median and mean wall-clock seconds per image (each setting compiled first).

No test image is used. The default's choice (5 random-walk sweeps per material update,
against 3) was made with:

    python experiments/select_smc.py --dataset data/fsclvr-lo --model data/models/fsclvr-lo --images 30 \\
        --configs '{"walk3": {"mcmc_steps": 3, "material_every": 3}, "walk5": {}}'
"""
from __future__ import annotations

import argparse
import json
import time
from dataclasses import replace

import jax
import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.attributes import AttributeRules, chromaticity, reflectance
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.evidence import shape_weights
from mitsuba_p3.infer.hypotheses import hypotheses_of
from mitsuba_p3.infer.smc import SMCConfig, sample_smc
from mitsuba_p3.shapes import SHAPES


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--images", type=int, default=30, help="evenly spaced train images")
    parser.add_argument("--configs", default='{"default": {}}', help="JSON: name -> SMCConfig fields")
    parser.add_argument("--noise", default="fitted", help="the model's noise model: fitted or robust")
    parser.add_argument("--size", choices=("small", "large"), help="only train objects of this size")
    parser.add_argument("--colours", help="only train objects of these colours (comma-separated: gray,brown)")
    parser.add_argument("--shift", type=float, default=0.0,
                        help="move the evenly spaced images by this fraction of their spacing (0.5: a disjoint set)")
    args = parser.parse_args()

    configs = {name: SMCConfig(**fields) for name, fields in json.loads(args.configs).items()}
    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=args.noise), "mitsuba", *dataset.resolution)
    colours = None if args.colours is None else set(args.colours.split(","))
    shots = [s for s in dataset.split("train")
             if args.size in (None, s.cls.size) and (colours is None or s.cls.colour in colours)]
    count = min(args.images, len(shots))
    spacing = (len(shots) - 1) / max(count - 1, 1)
    shots = [shots[int(i) % len(shots)] for i in np.linspace(0, len(shots) - 1, count) + args.shift * spacing]
    rules = AttributeRules.from_materials(fitted.materials)
    constrain = jax.jit(core.prior.constrain)
    # compile every setting once, so that no setting's first image is charged for it
    for config in configs.values():
        sample_smc(core, core.observe(dataset.image(shots[0])), replace(config, max_temperatures=2))
    report = {"dataset": args.dataset, "images": len(shots), "noise": args.noise, "size": args.size,
              "colours": args.colours}
    for name, config in configs.items():
        space = hypotheses_of(core.prior, config.kinds)
        right, log_true, z_true, seconds, material, gap, colour, spread = [], [], [], [], [], [], [], []
        for i, shot in enumerate(shots):
            start = time.perf_counter()
            run = sample_smc(core, core.observe(dataset.image(shot)), config)
            seconds.append(time.perf_counter() - start)
            weights = shape_weights(run.statistics)
            modal = max(weights, key=weights.get)
            right.append(modal == shot.cls.shape)
            shiny = np.mean([v["shiny"] for h, v in run.statistics["hypotheses"].items() if h.split("/")[0] == modal])
            material.append(bool(shiny > 0.5) == (shot.cls.material == "metal"))
            log_true.append(float(np.log(max(weights[shot.cls.shape], 1e-12))))
            flat = run.positions.reshape(-1, run.positions.shape[-1])
            samples = {k: np.asarray(v) for k, v in constrain(flat).items()}
            samples["class"] = np.argmax(samples["class_probabilities"], axis=-1)
            colour.append(rules.decide(samples)["colour"] == shot.cls.colour)
            spread.append(float(np.mean(np.std(chromaticity(reflectance(samples)), axis=0))))
            z_true.append(max(v["log_evidence"] for h, v in run.statistics["hypotheses"].items()
                              if h.split("/")[0] == shot.cls.shape))
            rows = run.particles.rows
            mine = rows.log_evidence[[SHAPES[c] == shot.cls.shape for c in space.classes[rows.index]]]
            gap.append(float(np.ptp(mine)) if len(mine) > 1 else np.nan)
            print(f"{name} {i + 1}/{len(shots)} {shot.class_name}: {'ok' if right[-1] else 'WRONG'} "
                  f"(p true {np.exp(log_true[-1]):.3f}) "
                  f"{seconds[-1]:.1f} s, island gap {gap[-1]:.1f}, colour {'ok' if colour[-1] else 'WRONG'} "
                  f"(spread {spread[-1]:.3f})", flush=True)
        report[name] = {"shape": float(np.mean(right)), "material": float(np.mean(material)),
                        "colour": float(np.mean(colour)), "colour_spread": float(np.median(spread)),
                        "log_p_true": float(np.mean(log_true)),
                        "mean_log_z_true": float(np.mean(z_true)),
                        "island_gap": {"median": float(np.nanmedian(gap)), "p90": float(np.nanpercentile(gap, 90))}
                        if not np.all(np.isnan(gap)) else None,
                        "seconds": {"median": float(np.median(seconds)), "mean": float(np.mean(seconds))},
                        "config": {k: v for k, v in vars(config).items() if v != getattr(SMCConfig(), k)}}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
