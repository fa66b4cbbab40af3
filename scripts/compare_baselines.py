"""P3 and NP3 against a baseline, cell by cell, with the intervals.

Reads a ``reproduce`` output folder (its ``accuracy.csv`` for P3/NP3 and every run's
``baselines/*.json``) and prints a markdown table per benchmark: each few-shot cell's accuracy
of P3 and NP3 (``--noise``, the headline's fitted noise by default) and of the baseline rows
named by ``--baselines`` (a substring of their label), with the 95% half-widths, and which is
ahead: ``=`` where the difference lies inside the two intervals' combined half-width
(sqrt(h1^2 + h2^2)), else the leader's name.

    python scripts/compare_baselines.py results/lo [--baselines frozen] [--noise fitted]
"""
from __future__ import annotations

import argparse
import csv
import json
from pathlib import Path

import numpy as np

SETTINGS = ("5-way 1-shot", "5-way 5-shot", "10-way 1-shot", "10-way 5-shot")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("results", type=Path)
    parser.add_argument("--baselines", default="frozen", help="substring of the baseline labels to compare")
    parser.add_argument("--noise", default="fitted")
    args = parser.parse_args()

    ours = {}
    with open(args.results / "accuracy.csv") as handle:
        for row in csv.DictReader(handle):
            if row["sigma"] == args.noise and row["distance"] == "paper":      # the default distance
                ours[row["benchmark"], row["model"].upper(), row["setting"]] = (float(row["accuracy"]),
                                                                                float(row["half_width_95"]))
    theirs = {}
    for path in sorted(args.results.glob("runs/*/baselines/*.json")):
        result = json.loads(path.read_text())
        if args.baselines.lower() in result["model"].lower():
            benchmark = path.parent.parent.name.split("-")[0]
            for setting, cell in result["accuracy"].items():
                theirs[benchmark, result["model"], setting] = (cell["mean"], cell["half_width"])
    counts = {"ahead": 0, "behind": 0, "tied": 0}
    for benchmark in sorted({k[0] for k in theirs}):
        models = sorted({k[1] for k in theirs if k[0] == benchmark})
        print(f"\n**{benchmark}** (accuracy % ± 95% half-width; '=' : within the combined interval)\n")
        print("| setting | P3 | NP3 | " + " | ".join(models) + " | P3 vs | NP3 vs |")
        print("|---|---|---|" + "---|" * len(models) + "---|---|")
        for setting in SETTINGS:
            cells, verdicts = [], {}
            for name in ("P3", "NP3"):
                mine = ours.get((benchmark, name, setting))
                cells.append(f"{100 * mine[0]:.1f} ± {100 * mine[1]:.1f}" if mine else "-")
                for model in models:
                    other = theirs.get((benchmark, model, setting))
                    if not mine or not other:
                        continue
                    gap, width = mine[0] - other[0], np.hypot(mine[1], other[1])
                    verdict = "=" if abs(gap) <= width else (name if gap > 0 else "baseline")
                    counts["tied" if verdict == "=" else "ahead" if verdict == name else "behind"] += 1
                    verdicts.setdefault(name, []).append(f"{verdict} ({100 * gap:+.1f})")
            cells += [f"{100 * theirs[benchmark, m, setting][0]:.1f} ± {100 * theirs[benchmark, m, setting][1]:.1f}"
                      if (benchmark, m, setting) in theirs else "-" for m in models]
            print(f"| {setting} | " + " | ".join(cells) + " | " + " | ".join(", ".join(verdicts.get(n, ["-"]))
                                                                          for n in ("P3", "NP3")) + " |")
    print(f"\ncells where P3/NP3 is ahead of a baseline row beyond the intervals: {counts['ahead']}, behind: "
          f"{counts['behind']}, within: {counts['tied']}")


if __name__ == "__main__":
    main()
