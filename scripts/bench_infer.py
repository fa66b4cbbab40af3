"""Inference benchmark over a benchmark's test (or train) split: speed, attribute recovery and agreement across seeds.

For each sampler setting (``--configs``), samples the P3 posterior of every test image
(or ``--images N`` of them, evenly spaced, or the images ``--shots`` names) with ``--seeds`` seeds; with
``--split train`` the train images instead, where a setting is chosen (the test split is for final figures).
The posteriors come through the
evaluation's cached, resumable, parallel posterior jobs (``OUT/CONFIG-seedS``; a killed
run resumes), then prints JSON, the settings side by side:

- ``seconds_per_image``: median wall-clock seconds of one posterior (workers share the cores);
  ``run_seconds_per_image``: the wall-clock time of the first seed's whole run (workers'
  start-up included) over its images: what an image costs on this machine with ``--jobs``
  workers; measured only when the run started empty (null when it resumed);
- attribute recovery (:func:`mitsuba_p3.evaluate.metrics.attribute_recovery`, first seed):
  shape (all, large), material kind, size, colour, mean log p(true shape), shape ECE; the
  material kind also by the rule ``evaluate`` uses when the run holds train posteriors
  (``mitsuba-p3 evaluate ... --out OUT/smc-seed0`` adds them), learnt from those posteriors;
- ``convergence`` within the first seed's run (:func:`mitsuba_p3.evaluate.run.convergence`): the
  median R-hat across MH chains, or SMC's island gap (the spread of the leading hypothesis's
  independent runs' log evidence: median, p90, share above 10 nats);
- ``max_r_hat_across_seeds``: per image, the largest R-hat of shift, scale and colour with each
  seed's run as one chain; the median and the 90th percentile over images; ``r_hat_across_seeds``
  the same per parameter; ``island_gap_all_seeds`` the island gap over every seed's posteriors;
- ``log_evidence_spread``: for samplers that estimate an evidence (none of the MH settings), per
  image the largest spread (max - min across seeds) over hypotheses, median over images;
  ``log_evidence_spread_leading_hypothesis`` the same for the hypothesis that leads (the one the
  posterior is made of); ``modal_shape_same_across_seeds`` the share of images whose modal shape
  every seed agrees on; ``by_seed`` each seed's shape and material accuracy and shape ECE;
- ``per_image``: each image's true shape, the first seed's modal shape and its probability of the truth.

Settings: ``smc-fields`` is the default of ``infer`` (tempered SMC over the shape classes under the
shading fields' form, ``--noise fields``); ``smc-fields-one-round`` the same with one round of runs (the
default sampler before 2026-11-28, ``SMCConfig.rounds``); ``smc`` the default sampler under the fitted
Gaussian noise model with hard shadows (the default likelihood before 2026-11-27); ``smc-robust`` the same with the fitted
inlier/outlier mixture; ``smc-persistent`` and ``smc-wastefree`` the default with persistent
sampling or waste-free SMC (8 sweeps kept from 32 of 256 particles); ``smc-narrow`` the default without its
coarse wide start, rendered turns, chart walk or window term (the default before 2026-11-26); ``smc-window-alone``
the default scoring a scene whose object left the window by the window alone (the default until 2026-11-27,
``SMCConfig.inside_window``); ``smc-unfolded`` the default
with the walk in z, not in a symmetry chart (the default before the chart walk); ``smc-jump`` the default with
the material kind's jump; ``smc-fields-rounds4`` the default with up to four rounds of runs where the answer
stays open (a seed's first two rounds are the default's own runs); ``smc-fields-tempered`` the default with each
run's evidence the tempered estimate alone (the default before the importance-sampling estimate, ``SMCConfig.importance``);
``mh-paper`` the MH evaluation preset with the paper's likelihood
(sigma 1, no shadows), the project's old default; ``mh-fitted`` that sampler with the fitted
noise. ``NAME:S`` runs a setting with S seeds instead of ``--seeds``. Needs a benchmark folder
and a model fitted to it:

    mitsuba-p3 benchmark generate fsclvr --out data/fsclvr
    mitsuba-p3 fit data/fsclvr --out data/models/fsclvr
    python scripts/bench_infer.py [--dataset data/fsclvr] [--model data/models/fsclvr] [--out out/bench-infer]
        [--configs smc-fields,smc-fields-one-round] [--seeds 4] [--images 120 | --shots 24,25] [--split test] [--jobs 2]
"""
from __future__ import annotations

import argparse
import json
import os
import time
from dataclasses import asdict, replace
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate import (PRESET, CachedPosterior, EvaluationConfig, check_run, compute_posteriors,
                                 posterior_path)
from mitsuba_p3.evaluate.jobs import PosteriorMisfits, rules_with_train_posteriors
from mitsuba_p3.evaluate.metrics import attribute_recovery
from mitsuba_p3.evaluate.run import convergence
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.smc import SMCConfig

CONFIGS = {"mh-paper": {"noise": "paper"}, "mh-fitted": {"noise": "fitted"},
           "smc": {"noise": "fitted", "sampler": SMCConfig()}, "smc-robust": {"noise": "robust", "sampler": SMCConfig()},
           # the moves compared against the default: persistent sampling, waste-free SMC
           "smc-persistent": {"noise": "fitted", "sampler": SMCConfig(persistent=True, wide_steps=0)},
           "smc-wastefree": {"noise": "fitted", "sampler": SMCConfig(waste_free=8, particles=256, wide_steps=0)},
           "smc-narrow": {"noise": "fitted", "sampler": SMCConfig(wide_steps=0, symmetry="free", chart=False,
                                                                  inside_window=False)},
           "smc-window-alone": {"noise": "fitted", "sampler": SMCConfig(inside_window=False)},
           "smc-unfolded": {"noise": "fitted", "sampler": SMCConfig(chart=False)},
           "smc-jump": {"noise": "fitted", "sampler": SMCConfig(jump=True)},
           "smc-fields": {"noise": "fields", "sampler": SMCConfig()},
           "smc-fields-one-round": {"noise": "fields", "sampler": SMCConfig(rounds=1)},
           "smc-fields-rounds4": {"noise": "fields", "sampler": SMCConfig(rounds=4)},
           "smc-fields-tempered": {"noise": "fields", "sampler": SMCConfig(importance=0)}}
CHECKED = ("shift", "scale", "colour")


def r_hat_across_seeds(runs: list[CachedPosterior]) -> dict:
    """Per checked parameter (shift, scale, colour) the largest rank R-hat over its coordinates, each
    seed's draws one chain (shift only where the cache holds its draws)."""
    import arviz as az

    worst = {}
    for name in CHECKED:
        if name == "shift" and any(run.shift_samples is None for run in runs):
            continue
        draws = [run.shift_samples if name == "shift" else run.program.samples[name] for run in runs]
        length = min(len(d) for d in draws)
        values = np.stack([d[:length] for d in draws])            # (seeds, draws, dims)
        worst[name] = max(float(az.rhat(values[..., dim], method="rank")) for dim in range(values.shape[-1]))
    return worst


def _evidence_per_image(runs: list[dict]) -> list[np.ndarray] | None:
    """Per image, the log evidence of every hypothesis under every seed, (seeds, hypotheses); None
    for samplers without an evidence or a single seed."""
    first = next(iter(runs[0].values()), None)
    if len(runs) < 2 or first is None or first.log_evidence is None:
        return None
    return [np.stack([run[i].log_evidence for run in runs]) for i in runs[0]]


def _evidence_spread(runs: list[dict]) -> float | None:
    """Median over images of the largest (over hypotheses) spread (max - min) of log evidence across seeds."""
    evidence = _evidence_per_image(runs)
    return None if evidence is None else float(np.median([np.max(np.ptp(e, axis=0)) for e in evidence]))


def _leading_evidence_spread(runs: list[dict]) -> float | None:
    """Median over images of the spread across seeds of the log evidence of the hypothesis that leads
    (highest mean log evidence over the seeds): the one that carries the posterior. Printed beside
    :func:`_evidence_spread`, which takes the worst hypothesis, often one the image rules out."""
    evidence = _evidence_per_image(runs)
    return None if evidence is None else float(
        np.median([np.ptp(e[:, int(np.argmax(e.mean(axis=0)))]) for e in evidence]))


def _modal_shape_agreement(runs: list[dict]) -> float:
    """Share of images whose modal shape class is the same under every seed."""
    modal = lambda p: int(np.bincount(np.asarray(p.program.samples["class"], int).ravel()).argmax())  # noqa: E731
    return float(np.mean([len({modal(run[i]) for run in runs}) == 1 for i in runs[0]]))


def _image_reading(shot, posterior: CachedPosterior) -> dict:
    """One image's reading under the first seed: its file, true shape, the posterior's modal shape and the
    probability it gives the true one."""
    from mitsuba_p3.shapes import SHAPES

    classes = np.asarray(posterior.program.samples["class"], int).ravel()
    shares = np.bincount(classes, minlength=len(SHAPES)) / len(classes)
    return {"file": str(shot.file.relative_to(shot.file.parents[2])), "shape": shot.cls.shape,
            "read": SHAPES[int(shares.argmax())], "p_true": round(float(shares[SHAPES.index(shot.cls.shape)]), 3)}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--out", type=Path, default=Path("out/bench-infer"))
    parser.add_argument("--configs", default="smc-fields,smc-fields-one-round")
    parser.add_argument("--seeds", type=int, default=4)
    parser.add_argument("--images", type=int, default=None, help="evenly spaced images of the split (default: all)")
    parser.add_argument("--shots", default=None, help="comma-separated image indices of the split, in place of --images")
    parser.add_argument("--split", choices=("test", "train"), default="test",
                        help="the split to sample: train to choose a setting, test (the default) for final figures")
    parser.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)))
    args = parser.parse_args()
    chosen = {c.partition(":")[0]: int(c.partition(":")[2] or args.seeds) for c in args.configs.split(",")}
    unknown = [c for c in chosen if c not in CONFIGS]
    if unknown:
        parser.error(f"unknown settings {unknown}; choose from {', '.join(CONFIGS)}")
    if args.images and args.shots is not None:
        parser.error("give --images or --shots, not both")
    dataset = load_dataset(args.dataset)
    images = dataset.split(args.split)
    if args.shots is not None:
        try:
            wanted = [int(i) for i in args.shots.split(",") if i.strip()]
        except ValueError:
            parser.error(f"--shots takes comma-separated image indices; got {args.shots!r}")
        if not wanted:
            parser.error("--shots names no image")
        unknown = sorted(set(wanted) - {s.index for s in images})
        if unknown:
            parser.error(f"--shots {unknown} are not images of the {args.split} split")
        images = [s for s in images if s.index in wanted]
    elif args.images:
        images = [images[i] for i in np.unique(np.linspace(0, len(images) - 1, args.images).astype(int))]
    rules = rules_for(FittedModel(args.model), dataset)
    misfits = PosteriorMisfits(dataset, Path(args.model))
    from mitsuba_p3.reproduce import machine

    report = {"dataset": args.dataset, "split": args.split, "images": len(images), "seeds": args.seeds,
              "machine": machine(), "settings": {}}
    for name, seeds in chosen.items():
        runs = []
        for seed in range(seeds):
            run_dir = args.out / f"{name}-seed{seed}"
            settings = CONFIGS[name]
            sampler = replace(settings.get("sampler", PRESET), seed=seed)
            config = EvaluationConfig(likelihoods=("p3",), sampler=sampler, jobs=args.jobs, noise=settings["noise"])
            check_run(run_dir, dataset, Path(args.model), config)
            fresh = not any(posterior_path(run_dir, "p3", s.index).exists() for s in images)
            start = time.perf_counter()
            compute_posteriors(dataset, Path(args.model), run_dir, config, shots=[s.index for s in images],
                               progress=lambda d, t: print(f"\r{name} seed {seed}: {d}/{t}", end="", flush=True))
            print(flush=True)
            if seed == 0:
                run_seconds = (time.perf_counter() - start) / len(images) if fresh else None
            runs.append({s.index: CachedPosterior.load(posterior_path(run_dir, "p3", s.index), 500) for s in images})
        _, recovered = attribute_recovery(dataset, runs[0], rules, misfits)     # the model's rules may read the misfit
        # (learnt from train posteriors, it would score the images it learnt from on the train split)
        learnt = rules if args.split == "train" else rules_with_train_posteriors(rules, dataset, args.out / f"{name}-seed0",
                                                                                 "p3", misfits)
        if learnt is not rules:
            recovered["material_accuracy_train_posterior_rule"] = attribute_recovery(
                dataset, runs[0], learnt, misfits)[1]["material_accuracy"]
        seconds = [p.seconds for run in runs for p in run.values()]
        entry = {"sampler": asdict(sampler), "seconds_per_image": float(np.median(seconds)),
                 "run_seconds_per_image": run_seconds,
                 **{k: round(v, 4) for k, v in recovered.items()},
                 # each sampler's own within-run diagnostic: R-hat across MH chains, SMC's island gap
                 **convergence(runs[0].values()),
                 "log_evidence_spread": _evidence_spread(runs)}
        entry["seeds"] = seeds
        entry["per_image"] = [_image_reading(shot, runs[0][shot.index]) for shot in images]
        if seeds > 1:
            per_image = [r_hat_across_seeds([run[s.index] for run in runs]) for s in images]
            r_hats = [max(r.values()) for r in per_image]
            entry["max_r_hat_across_seeds_median"] = float(np.median(r_hats))
            entry["max_r_hat_across_seeds_p90"] = float(np.percentile(r_hats, 90))
            # per parameter (the targets: each <= 1.05), median and p90 over images
            entry["r_hat_across_seeds"] = {name: {"median": float(np.median(v)), "p90": float(np.percentile(v, 90))}
                                           for name in CHECKED
                                           if (v := [r[name] for r in per_image if name in r])}
            # the island gap over every seed's posteriors (convergence above is the first seed's)
            entry["island_gap_all_seeds"] = {k.removeprefix("island_gap_"): v for k, v in
                                             convergence([p for run in runs for p in run.values()]).items()
                                             if k.startswith("island_gap")}
            entry["log_evidence_spread_leading_hypothesis"] = _leading_evidence_spread(runs)
            entry["modal_shape_same_across_seeds"] = _modal_shape_agreement(runs)
            # each seed's own attribute recovery: how much the answer depends on the seed
            by_seed = [recovered] + [attribute_recovery(dataset, run, rules, misfits)[1] for run in runs[1:]]
            entry["by_seed"] = {key: [round(r[key], 4) for r in by_seed]
                                for key in ("shape_accuracy", "material_accuracy", "shape_ece")}
        report["settings"][name] = entry
        print(json.dumps({name: entry}), flush=True)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
