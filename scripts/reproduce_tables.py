"""Reproduce the paper's accuracy and ADI tables on this project's benchmarks.

For fsclvr, dark and room: generate the benchmark (if missing), fit a model to
it (if missing) and evaluate P3 and NP3 on its test split; ood is evaluated with
the fsclvr model, as in the paper. Every step resumes: benchmarks, fits and
per-image posteriors already on disk are reused. Writes, in ``--out``:

- ``accuracy.md`` / ``accuracy.csv``: the paper's layout (rows: models; columns:
  benchmarks; cells: 5-way 1-shot / 5-way 5-shot / 10-way 1-shot / 10-way 5-shot
  accuracy in %), this project's numbers beside the paper's;
- ``adi.md`` / ``adi.csv``: mean ADI (metres) per benchmark, P3 / NP3, beside the paper's;
- one evaluation run folder per benchmark (``runs/V``) with its own tables and figures.

Baselines evaluated into ``runs/V`` beforehand (``mitsuba-p3 baseline evaluate
TRAINED data/V --out results/runs/V``) appear in the accuracy table too.

    python scripts/reproduce_tables.py [--data data] [--out results] [--episodes 100] [--jobs CORES]
        [--chains 8 --steps 200 ...] [--benchmarks fsclvr,dark,room,ood] [--likelihoods p3,np3] [--sigma S]
        [--distance all|colour+class|...]

``--sigma`` replaces the paper's colour-likelihood sigma (choose it on the train
classes with ``scripts/select_sigma.py``); such runs go to ``runs/V-sigmaS`` and
get their own rows in the tables. ``--distance colour+class`` scores the same
posteriors with fewer distance terms (choose them on the train classes with
``scripts/select_distance.py``); its tables go to ``runs/V/distance-colour+class``
and get their own rows ("NP3 (colour+class)"); nothing is resampled.

The sampler settings default to a lighter preset than ``mitsuba-p3 infer`` (see
``PRESET``): 840 posteriors (420 images x P3/NP3) at the inference defaults
would take about 8 hours on the 2-core machine.
"""
from __future__ import annotations

import argparse
import csv
import json
import os
import subprocess
import sys
import time
from pathlib import Path

from mitsuba_p3.concepts import DistanceConfig, parse_properties
from mitsuba_p3.errors import MitsubaP3Error
from mitsuba_p3.evaluate import SETTINGS, EvaluationConfig, evaluate, load_baselines, markdown_table
from mitsuba_p3.infer.mcmc import SamplerConfig

# Lighter sampling for the 840 evaluation posteriors (measured: see the README).
PRESET = dict(chains=8, steps=200, burn_in=30, tune_rounds=3, tune_steps=40)

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


def run(command: list[str]) -> None:
    print("+", " ".join(command), flush=True)
    subprocess.run(command, check=True)


def prepare(data: Path, variant: str) -> tuple[Path, Path]:
    """The benchmark folder and the model folder evaluation uses (made when missing)."""
    cli = [sys.executable, "-m", "mitsuba_p3.cli"]
    folder = data / variant
    run(cli + ["benchmark", "generate", variant, "--out", str(folder)])  # renders only what is missing
    fitted_on = "fsclvr" if variant == "ood" else variant
    model = data / "models" / fitted_on
    if not (model / "model.json").exists():
        run(cli + ["fit", str(data / fitted_on), "--out", str(model)])
    return folder, model


def cells(result: dict) -> str:
    names = [f"{n}-way {k}-shot" for n, k in SETTINGS]
    return "/".join(f"{100 * result['accuracy'][n]['mean']:.1f}" if n in result["accuracy"] else "-" for n in names)


def run_name(variant: str, sigma: float | None) -> str:
    """The run folder of a benchmark: ``V`` at the paper's sigma, ``V-sigmaS`` at another."""
    return variant if sigma is None else f"{variant}-sigma{sigma:g}"


def parse_run_name(name: str) -> tuple[str, float | None] | None:
    """(benchmark, sigma) of a run folder name, or None for a folder this script did not make."""
    variant, _, rest = name.partition("-sigma")
    if variant not in COLUMNS:
        return None
    try:
        return variant, (float(rest) if rest else None)
    except ValueError:
        return None


def label(likelihood: str, sigma: float | None, distance: str | None = None) -> str:
    """A table row's name: ``P3``, ``P3 (sigma 0.3)``, ``NP3 (colour+class)``, ..."""
    notes = ([] if sigma is None else [f"sigma {sigma:g}"]) + ([] if distance is None else [distance])
    return likelihood.upper() + (f" ({', '.join(notes)})" if notes else "")


def collect(out: Path) -> dict:
    """Every evaluated run under ``out/runs``: {(benchmark, sigma, distance): {likelihood: result}}, where
    distance is None for the paper's and e.g. ``colour+class`` for tables in ``runs/V/distance-colour+class``."""
    found = {}
    for run in sorted((out / "runs").glob("*/")):
        key = parse_run_name(run.name)
        for path in [run / "results.json", *sorted(run.glob("distance-*/results.json"))] if key else []:
            if path.is_file():
                distance = None if path.parent == run else path.parent.name.removeprefix("distance-")
                found[key + (distance,)] = json.loads(path.read_text())["results"]
    return found


def write_tables(out: Path, results: dict) -> None:
    """The accuracy and ADI tables in the paper's layout, from ``collect``'s runs."""
    variants = sorted({(s, d) for _, s, d in results}, key=lambda v: (v[0] is not None, v[0] or 0, v[1] or ""))
    models = [(m, s, d) for s, d in variants for m in ("p3", "np3")
              if any(m in r for (_, *v), r in results.items() if tuple(v) == (s, d))]
    get = lambda c, m, s, d: results.get((c, s, d), {}).get(m)  # noqa: E731
    header = ["model", "source"] + [TITLES[c] for c in COLUMNS]
    rows = [[label(m, s, d), "this project"] + [cells(get(c, m, s, d)) if get(c, m, s, d) else "-" for c in COLUMNS]
            for m, s, d in models]
    found = {}
    for c, s, d in results:
        if s is None and d is None:
            for baseline in load_baselines(out / "runs" / c):
                found.setdefault(baseline["model"], {})[c] = baseline
    for model, per_benchmark in sorted(found.items()):
        rows.append([model, "this project"] + [cells(per_benchmark[c]) if c in per_benchmark else "-"
                                               for c in COLUMNS])
    for model, numbers in PAPER_ACCURACY.items():
        rows.append([model, "paper"] + [numbers[c] for c in COLUMNS])
    note = ("\nCells: 5-way 1-shot / 5-way 5-shot / 10-way 1-shot / 10-way 5-shot accuracy (%). "
            "OOD has 10 test classes. Rows without a sigma use the paper's colour-likelihood sigma (1.0; 0.35 "
            "for DARK); rows without distance terms use the paper's distance (all seven terms). Sigma and "
            "distance terms were chosen on train classes (scripts/select_sigma.py, scripts/select_distance.py). "
            "The paper's numbers are on its own data sets: compare in spirit.\n")
    (out / "accuracy.md").write_text(markdown_table(header, rows) + note)
    with open(out / "accuracy.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "sigma", "distance", "setting", "accuracy", "half_width_95", "ece",
                         "paper"])
        for c in COLUMNS:
            for m, s, d in models:
                if not get(c, m, s, d):
                    continue
                paper = PAPER_ACCURACY[m.upper()][c].split("/")
                for i, (n, k) in enumerate(SETTINGS):
                    a = get(c, m, s, d)["accuracy"].get(f"{n}-way {k}-shot")
                    if a:
                        writer.writerow([c, m, "paper" if s is None else s, d or "paper", f"{n}-way {k}-shot",
                                         a["mean"], a["half_width"], a["ece"], float(paper[i]) / 100])
    # ADI depends on the posteriors only, not on the distance: one column per (model, sigma)
    pose_models = [(m, s) for m, s, d in models if d is None]
    header = ["benchmark"] + [f"{label(m, s)} mean ADI (m)" for m, s in pose_models] + ["paper P3 / NP3"]
    adi = lambda c, m, s: f"{get(c, m, s, None)['adi']['mean']:.4f}" if get(c, m, s, None) else "-"  # noqa: E731
    rows = [[TITLES[c]] + [adi(c, m, s) for m, s in pose_models] + [f"{PAPER_ADI[c][0]:.4f} / {PAPER_ADI[c][1]:.4f}"]
            for c in COLUMNS if any(v == c for v, _, _ in results)]
    (out / "adi.md").write_text(markdown_table(header, rows))
    with open(out / "adi.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "sigma", "mean_adi_m", "median_adi_m", "paper_mean_adi_m"])
        for c in COLUMNS:
            for m, s in pose_models:
                if get(c, m, s, None):
                    a = get(c, m, s, None)["adi"]
                    writer.writerow([c, m, "paper" if s is None else s, a["mean"], a["median"],
                                     PAPER_ADI[c][("p3", "np3").index(m)]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--benchmarks", default=",".join(("fsclvr", "dark", "room", "ood")))
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=len(os.sched_getaffinity(0)),
                        help="parallel posterior workers; they share the cores (default: one per core)")
    parser.add_argument("--likelihoods", default="p3,np3", help="comma-separated: p3, np3 or both")
    for name, value in PRESET.items():
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=value)
    parser.add_argument("--sigma", type=float, default=None,
                        help="colour-likelihood sigma (default: the paper's); runs go to runs/V-sigmaS")
    parser.add_argument("--distance", default="all",
                        help="distance terms: 'all' (the paper's) or e.g. colour+class; reuses the posteriors, "
                             "tables go to runs/V/distance-TERMS")
    args = parser.parse_args()
    if args.sigma is not None and not args.sigma > 0:
        parser.error("--sigma must be positive")
    try:
        distance = DistanceConfig(properties=parse_properties(args.distance))
    except MitsubaP3Error as error:
        parser.error(str(error))
    sampler = SamplerConfig(**{name: getattr(args, name) for name in PRESET})
    args.out.mkdir(parents=True, exist_ok=True)
    timing_log = args.out / "timing.json"
    started, total, invocation = time.strftime("%Y-%m-%dT%H:%M:%S"), 0.0, time.perf_counter()
    for variant in args.benchmarks.split(","):
        start = time.perf_counter()
        folder, model = prepare(args.data, variant)
        prepared = (time.perf_counter() - start) / 60
        start = time.perf_counter()
        config = EvaluationConfig(likelihoods=tuple(args.likelihoods.split(",")), sigma=args.sigma, sampler=sampler,
                                  episodes=args.episodes, jobs=args.jobs, distance=distance)
        evaluate(folder, model, args.out / "runs" / run_name(variant, args.sigma), config,
                 progress=lambda phase, done, total: print(f"\r{variant} {phase}: {done}/{total}", end="", flush=True))
        minutes = (time.perf_counter() - start) / 60
        total += minutes
        print(f"\n{variant}: {minutes:.1f} min", flush=True)
        # the tables cover every benchmark and sigma evaluated so far, this run's included
        write_tables(args.out, collect(args.out))
        # wall-clock minutes per invocation, appended: a resumed reproduction adds its parts up
        log = json.loads(timing_log.read_text()) if timing_log.is_file() else []
        log.append({"invocation": started, "benchmark": variant, "likelihoods": args.likelihoods, "sigma": args.sigma,
                    "distance": args.distance, "jobs": args.jobs,
                    "episodes": args.episodes, "minutes": round(minutes, 2),
                    "generate_and_fit_minutes": round(prepared, 2),
                    "sampler": {k: getattr(args, k) for k in PRESET}})
        timing_log.write_text(json.dumps(log, indent=1))
    print((args.out / "accuracy.md").read_text())
    print((args.out / "adi.md").read_text())
    print(f"posteriors and episodes of {args.benchmarks}: {total:.1f} min (benchmark generation and fits excluded); "
          f"the whole invocation: {(time.perf_counter() - invocation) / 60:.1f} min")


if __name__ == "__main__":
    main()
