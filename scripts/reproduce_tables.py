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

    python scripts/reproduce_tables.py [--data data] [--out results] [--episodes 100] [--jobs 1]
        [--chains 8 --steps 200 ...] [--benchmarks fsclvr,dark,room,ood] [--likelihoods p3,np3]

The sampler settings default to a lighter preset than ``mitsuba-p3 infer`` (see
``PRESET``): 840 posteriors (420 images x P3/NP3) at the inference defaults
would take about 8 hours on the 2-core machine.
"""
from __future__ import annotations

import argparse
import csv
import json
import subprocess
import sys
import time
from pathlib import Path

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


def write_tables(out: Path, results: dict) -> None:
    header = ["model", "source"] + [TITLES[c] for c in COLUMNS]
    rows = []
    for model in ("P3", "NP3"):
        rows.append([model, "this project"] + [cells(results[c][model.lower()]) if model.lower() in results.get(c, {})
                                               else "-" for c in COLUMNS])
    found = {}
    for c in results:
        for baseline in load_baselines(out / "runs" / c):
            found.setdefault(baseline["model"], {})[c] = baseline
    for model, per_benchmark in sorted(found.items()):
        rows.append([model, "this project"] + [cells(per_benchmark[c]) if c in per_benchmark else "-"
                                               for c in COLUMNS])
    for model, numbers in PAPER_ACCURACY.items():
        rows.append([model, "paper"] + [numbers[c] for c in COLUMNS])
    note = ("\nCells: 5-way 1-shot / 5-way 5-shot / 10-way 1-shot / 10-way 5-shot accuracy (%). "
            "OOD has 10 test classes. The paper's numbers are on its own data sets: compare in spirit.\n")
    (out / "accuracy.md").write_text(markdown_table(header, rows) + note)
    with open(out / "accuracy.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "setting", "accuracy", "half_width_95", "ece", "paper"])
        for c in COLUMNS:
            if c not in results:
                continue
            for model in (m for m in ("p3", "np3") if m in results[c]):
                paper = PAPER_ACCURACY[model.upper()][c].split("/")
                for i, (n, k) in enumerate(SETTINGS):
                    a = results[c][model]["accuracy"].get(f"{n}-way {k}-shot")
                    if a:
                        writer.writerow([c, model, f"{n}-way {k}-shot", a["mean"], a["half_width"], a["ece"],
                                         float(paper[i]) / 100])
    header = ["benchmark", "P3 mean ADI (m)", "NP3 mean ADI (m)", "paper P3 / NP3"]
    adi = lambda c, m: f"{results[c][m]['adi']['mean']:.4f}" if m in results[c] else "-"  # noqa: E731
    rows = [[TITLES[c], adi(c, "p3"), adi(c, "np3"), f"{PAPER_ADI[c][0]:.4f} / {PAPER_ADI[c][1]:.4f}"]
            for c in COLUMNS if c in results]
    (out / "adi.md").write_text(markdown_table(header, rows))
    with open(out / "adi.csv", "w", newline="") as f:
        writer = csv.writer(f)
        writer.writerow(["benchmark", "model", "mean_adi_m", "median_adi_m", "paper_mean_adi_m"])
        for c in COLUMNS:
            if c in results:
                for i, model in enumerate(("p3", "np3")):
                    if model in results[c]:
                        a = results[c][model]["adi"]
                        writer.writerow([c, model, a["mean"], a["median"], PAPER_ADI[c][i]])


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--data", type=Path, default=Path("data"))
    parser.add_argument("--out", type=Path, default=Path("results"))
    parser.add_argument("--benchmarks", default=",".join(("fsclvr", "dark", "room", "ood")))
    parser.add_argument("--episodes", type=int, default=100)
    parser.add_argument("--jobs", type=int, default=1)
    parser.add_argument("--likelihoods", default="p3,np3", help="comma-separated: p3, np3 or both")
    for name, value in PRESET.items():
        parser.add_argument("--" + name.replace("_", "-"), type=int, default=value)
    args = parser.parse_args()
    sampler = SamplerConfig(**{name: getattr(args, name) for name in PRESET})
    args.out.mkdir(parents=True, exist_ok=True)
    # the tables cover every benchmark evaluated so far: earlier runs' results, replaced by this run's
    results, timing_log = {}, args.out / "timing.json"
    for variant in COLUMNS:
        earlier = args.out / "runs" / variant / "results.json"
        if earlier.is_file():
            results[variant] = json.loads(earlier.read_text())["results"]
    for variant in args.benchmarks.split(","):
        folder, model = prepare(args.data, variant)
        start = time.perf_counter()
        config = EvaluationConfig(likelihoods=tuple(args.likelihoods.split(",")), sampler=sampler,
                                  episodes=args.episodes, jobs=args.jobs)
        results[variant] = evaluate(folder, model, args.out / "runs" / variant, config,
                                    progress=lambda phase, done, total: print(f"\r{variant} {phase}: {done}/{total}",
                                                                              end="", flush=True))
        minutes = (time.perf_counter() - start) / 60
        print(f"\n{variant}: {minutes:.1f} min", flush=True)
        write_tables(args.out, results)
        # wall-clock minutes per invocation, appended: a resumed reproduction adds its parts up
        log = json.loads(timing_log.read_text()) if timing_log.is_file() else []
        log.append({"benchmark": variant, "likelihoods": args.likelihoods, "jobs": args.jobs,
                    "episodes": args.episodes, "minutes": round(minutes, 2),
                    "sampler": {k: getattr(args, k) for k in PRESET}})
        timing_log.write_text(json.dumps(log, indent=1))
    print((args.out / "accuracy.md").read_text())
    print((args.out / "adi.md").read_text())


if __name__ == "__main__":
    main()
