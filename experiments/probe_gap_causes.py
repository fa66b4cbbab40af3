"""What an evaluation's island gaps are made of: runs that missed the optimum, or the evidence estimate's noise.

The island gap (the spread of the leading hypothesis's independent runs' log evidence) is issue 40's measure of
a posterior's agreement with itself. A gap has two causes: a run that settled on a worse optimum (its best log
likelihood falls short of the other run's), or two runs that found the same optimum and still estimate its
evidence differently (the tempered SMC estimate's variance, which falls with more particles or sweeps, not with
better moves). This reads an evaluation's cached posteriors, no sampling: per image the gap, the spread of the
best log likelihood among the leader's runs, and the leader's margin over the runner-up hypothesis (a gap
smaller than the margin cannot change the decided shape). Prints the summary over images with gaps over
``--over`` nats.

    python experiments/probe_gap_causes.py out/eval-room-tinted [--over 10]
"""
from __future__ import annotations

import argparse
import csv
from pathlib import Path

import numpy as np

from mitsuba_p3.evaluate.jobs import posterior_path


def gap_causes(path: Path) -> dict:
    """The island gap of one cached posterior, the leader's runs' best-log-likelihood spread, and its margin."""
    with np.load(path) as f:
        gap, index = float(f["island_gap"]), f["particles_index"]
        evidence, loglik = f["particles_log_evidence"], f["particles_loglikelihood"]
    leader = index[np.argmax(evidence)]
    best = loglik[index == leader].max(axis=1)
    others = evidence[index != leader]
    return {"gap": gap, "best_spread": float(best.max() - best.min()),
            "margin": float(evidence.max() - others.max()) if others.size else float("inf")}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("run", type=Path, help="an evaluation run (its posteriors and attributes.csv)")
    parser.add_argument("--over", type=float, default=10.0, help="the gaps to look at, in nats")
    parser.add_argument("--likelihood", default="p3")
    args = parser.parse_args()
    with open(args.run / "attributes.csv", newline="") as handle:
        rows = [r for r in csv.DictReader(handle) if r["model"] == args.likelihood]
    found = [(r, gap_causes(posterior_path(args.run, args.likelihood, int(r["query"])))) for r in rows]
    big = [(r, c) for r, c in found if c["gap"] > args.over]
    print(f"{args.run}: {len(big)} of {len(found)} test posteriors with an island gap over {args.over:g} nats")
    if not big:
        return
    median = lambda key, group: float(np.median([c[key] for _, c in group]))  # noqa: E731
    print(f"  best log likelihood's spread among the leader's runs, median: {median('best_spread', big):.1f} nats "
          f"(all images: {median('best_spread', found):.1f})")
    print(f"  runs within 3 nats of each other's best (the estimate's noise): "
          f"{sum(c['best_spread'] < 3 for _, c in big)}; a run short by more: {sum(c['best_spread'] >= 3 for _, c in big)}")
    print(f"  leader's margin over the runner-up, median: {median('margin', big):.1f} nats; gaps as large as the margin: "
          f"{sum(c['margin'] <= c['gap'] for _, c in big)}")
    for r, c in sorted(big, key=lambda rc: -rc[1]["gap"]):
        print(f"    {r['query']:>5} {r['class']:<28} gap {c['gap']:6.1f}  best spread {c['best_spread']:6.1f}  "
              f"margin {c['margin']:7.1f}  shape {r['shape_decided']}{'' if r['shape_decided'] == r['shape_true'] else ' (wrong)'}")


if __name__ == "__main__":
    main()
