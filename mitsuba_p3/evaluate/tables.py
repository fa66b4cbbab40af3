"""The tables and figure of an evaluation run: accuracy and ADI as CSV and Markdown, a reliability plot."""
from __future__ import annotations

import csv
import json
from pathlib import Path

from ..concepts import PROPERTIES, DistanceConfig
from ..files import atomic_open, atomic_write
from .metrics import SETTINGS, setting_name


def tables_dir(run_dir: Path, distance: DistanceConfig) -> Path:
    """Where a run's tables for ``distance`` go: the run folder for the default distance (all
    terms, the default spread and KL direction), ``RUN/distance-colour+class`` (say) for another, its terms in the order of
    ``PROPERTIES`` (the distance is their sum), with ``-spreadN`` (``spread0``: no spread) for
    programs whose concept spread differs from the default, ``-kl-class-image`` (say) for the KL's
    other direction and ``-gaussian-concepts`` for Gaussian kernels; the posteriors are shared."""
    terms = [p for p in PROPERTIES if p in distance.properties]
    name = "" if tuple(terms) == PROPERTIES else "distance-" + "+".join(terms)
    if distance.spread_shots != DistanceConfig.spread_shots:
        name += ("-" if name else "") + f"spread{distance.spread_shots}"
    if distance.direction != DistanceConfig.direction:
        name += ("-" if name else "") + "kl-" + distance.direction.replace("||", "-")
    if distance.tails != DistanceConfig.tails and distance.spread_shots:
        name += ("-" if name else "") + ("concept-tails" if distance.tails else "gaussian-concepts")
    return Path(run_dir) / name if name else Path(run_dir)


def markdown_table(header: list[str], rows: list[list[str]]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return "\n".join(lines + ["| " + " | ".join(r) + " |" for r in rows]) + "\n"


def write_tables(run_dir: Path, results: dict, baselines_dir: Path | None = None) -> dict:
    """accuracy / adi / calibration as CSV and markdown, and the reliability plot, in ``run_dir``;
    baselines evaluated into ``baselines_dir`` (default ``run_dir``) join the accuracy table."""
    from ..plots import reliability_diagram

    settings = [setting_name(n, k) for n, k in SETTINGS]
    header = ["model"] + settings
    rows = []
    for likelihood, result in results.items():
        cells = []
        for name in settings:
            acc = result["accuracy"].get(name)
            cells.append(f"{100 * acc['mean']:.1f} ± {100 * acc['half_width']:.1f}" if acc else "-")
        rows.append([likelihood.upper()] + cells)
    baselines = load_baselines(baselines_dir or run_dir)
    for baseline in baselines:
        rows.append([baseline["model"]] + [
            f"{100 * a['mean']:.1f} ± {100 * a['half_width']:.1f}" if (a := baseline["accuracy"].get(name)) else "-"
            for name in settings])
    atomic_write(run_dir / "accuracy.md", markdown_table(header, rows))
    with atomic_open(run_dir / "accuracy.csv") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "setting", "accuracy", "half_width_95", "episodes", "ece"])
        for likelihood, result in results.items():
            for name, acc in result["accuracy"].items():
                writer.writerow([likelihood, name, acc["mean"], acc["half_width"], acc["episodes"], acc["ece"]])
        for baseline in baselines:
            for name, acc in baseline["accuracy"].items():
                writer.writerow([baseline["model"], name, acc["mean"], acc["half_width"], acc["episodes"], ""])

    classes = sorted({c for result in results.values() for c in result["adi_per_class"]})
    adi_rows = [[c] + [f"{result['adi_per_class'][c]['mean']:.4f} / {result['adi_per_class'][c]['median']:.4f}"
                       for result in results.values()] for c in classes]
    adi_rows.append(["**all**"] + [f"{r['adi']['mean']:.4f} / {r['adi']['median']:.4f}" for r in results.values()])
    atomic_write(run_dir / "adi.md", markdown_table(["class"] + [f"{k.upper()} mean / median (m)" for k in results],
                                              adi_rows))
    with atomic_open(run_dir / "adi.csv") as f:
        writer = csv.writer(f)
        writer.writerow(["model", "class", "mean_adi_m", "median_adi_m", "images"])
        for likelihood, result in results.items():
            for c, v in result["adi_per_class"].items():
                writer.writerow([likelihood, c, v["mean"], v["median"], v["images"]])
            writer.writerow([likelihood, "all", result["adi"]["mean"], result["adi"]["median"],
                             result["adi"]["images"]])
    reliability_diagram(run_dir / "reliability.png", results, settings)
    atomic_write(run_dir / "attributes.md", attribute_table(results))
    return {"accuracy": str(run_dir / "accuracy.md"), "adi": str(run_dir / "adi.md"),
            "attributes": str(run_dir / "attributes.md"), "reliability": str(run_dir / "reliability.png")}


ATTRIBUTE_COLUMNS = (("shape_accuracy", "shape %"), ("shape_accuracy_large", "shape, large %"),
                     ("material_accuracy", "material %"), ("size_accuracy", "size %"), ("colour_accuracy", "colour %"),
                     ("shape_log_score", "log p(true shape)"), ("shape_ece", "shape ECE"))


def attribute_table(results: dict) -> str:
    """Markdown: the attributes each model's posteriors recover (:func:`.metrics.attribute_recovery`)."""
    def cell(summary, key):
        if key not in summary:
            return "-"
        return f"{100 * summary[key]:.1f}" if "accuracy" in key else f"{summary[key]:.3f}"

    rows = [[model.upper()] + [cell(r.get("attributes", {}), key) for key, _ in ATTRIBUTE_COLUMNS]
            for model, r in results.items()]
    return markdown_table(["model"] + [title for _, title in ATTRIBUTE_COLUMNS], rows)


def load_baselines(run_dir: Path) -> list[dict]:
    """Baseline results evaluated on this run's episodes (``mitsuba-p3 baseline evaluate --out RUN``)."""
    return [json.loads(p.read_text()) for p in sorted(Path(run_dir).glob("baselines/*.json"))]
