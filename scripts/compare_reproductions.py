"""How far two ``mitsuba-p3 reproduce`` outputs of the same settings differ, cell by cell.

Two reproductions from the same benchmark folders are not bit-identical: a fit sums gradients in the
order the renderer's threads finish, so two fits of one benchmark differ in the sixth digit, and SMC's
resampling turns that into other draws. This script measures what that does to the tables, so that a
difference between two rows (NP3 against P3, say) can be read against the difference one row has with
itself:

    python scripts/compare_reproductions.py results/lo results/lo-cold

Prints, for every accuracy cell both folders hold, the two accuracies, their difference in points and
the 95% half-width; per run folder both hold, how often a test image's decided attributes agree (the
share of images, not the difference of two accuracies); and both mean ADIs.
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

ATTRIBUTES = ("shape", "material", "size", "colour")


def read_rows(path: Path) -> list[dict]:
    with open(path, newline="") as handle:
        return list(csv.DictReader(handle))


def accuracy_cells(folder: Path) -> dict[tuple, dict]:
    """(benchmark, model, sigma, distance, setting) -> the row of ``accuracy.csv`` (this project's rows)."""
    return {(r["benchmark"], r["model"], r["sigma"], r["distance"], r["setting"]): r
            for r in read_rows(folder / "accuracy.csv") if r["model"] in ("p3", "np3")}


def attribute_agreement(a: Path, b: Path) -> dict[str, dict[str, float]]:
    """Per likelihood, the share of the test images both runs decided on whose decided attribute agrees."""
    rows_a, rows_b = ({(r["model"], r["query"]): r for r in read_rows(f)} for f in (a, b))
    agreement = {}
    for model in sorted({m for m, _ in rows_a.keys() & rows_b.keys()}):
        common = [k for k in rows_a.keys() & rows_b.keys() if k[0] == model]
        agreement[model] = {name: sum(rows_a[k][f"{name}_decided"] == rows_b[k][f"{name}_decided"] for k in common)
                            / len(common) for name in ATTRIBUTES}
        agreement[model]["images"] = len(common)
    return agreement


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path, help="a reproduce output folder (accuracy.csv, runs/)")
    parser.add_argument("second", type=Path, help="another, made with the same settings")
    args = parser.parse_args(argv)
    for folder in (args.first, args.second):
        if not (folder / "accuracy.csv").is_file():
            parser.error(f"{folder} has no accuracy.csv: not a reproduce output folder")

    first, second = accuracy_cells(args.first), accuracy_cells(args.second)
    common = [key for key in first if key in second]     # in the first table's order
    if not common:
        parser.error("the two folders share no accuracy cell")
    print("| benchmark | model | noise | distance | setting | first | second | difference | 95% half-width |")
    print("|---|---|---|---|---|---|---|---|---|")
    differences = []
    for key in common:
        a, b = (100 * float(t[key]["accuracy"]) for t in (first, second))
        half = 100 * max(float(first[key]["half_width_95"]), float(second[key]["half_width_95"]))
        differences.append(abs(b - a))
        print(f"| {' | '.join(key)} | {a:.1f} | {b:.1f} | {b - a:+.1f} | {half:.1f} |")
    differences.sort()
    print(f"\n{len(common)} cells: |difference| median {differences[len(differences) // 2]:.1f}, "
          f"largest {differences[-1]:.1f} points\n")

    print("| run | likelihood | images | shape | material | size | colour |")
    print("|---|---|---|---|---|---|---|")
    for run in sorted(p.name for p in (args.first / "runs").iterdir() if (p / "attributes.csv").is_file()):
        a, b = args.first / "runs" / run / "attributes.csv", args.second / "runs" / run / "attributes.csv"
        if b.is_file():
            for model, agree in attribute_agreement(a, b).items():
                print(f"| {run} | {model} | {agree['images']} | "
                      + " | ".join(f"{100 * agree[name]:.1f}%" for name in ATTRIBUTES) + " |")

    adi = [{(r["benchmark"], r["model"], r["sigma"]): float(r["mean_adi_m"]) for r in read_rows(f / "adi.csv")}
           for f in (args.first, args.second)]
    print("\n| benchmark | model | noise | mean ADI (m), first | second |")
    print("|---|---|---|---|---|")
    for key in sorted(adi[0].keys() & adi[1].keys()):
        print(f"| {' | '.join(key)} | {adi[0][key]:.4f} | {adi[1][key]:.4f} |")

if __name__ == "__main__":
    main()
