"""Attribute recovery on *train* posteriors: score a fit or a sampler choice without the test split.

An evaluation run caches the posteriors of the first train images of every class (the concept
spread's; ``experiments/sample_train_shots.py`` samples more). This scores them as
``mitsuba-p3 evaluate`` scores the test split (:func:`~mitsuba_p3.evaluate.metrics.attribute_recovery`,
with the rule learnt from the fit's materials, the one ``mitsuba-p3 infer`` uses) and lists the
misread images and the island gaps (and the shape's log score per true material kind), so two fits or two
samplers are compared on train classes only. Several runs, each
with its own model, print side by side:

    python experiments/score_train_attributes.py data/fsclvr-lo \\
        --run out/train-free=data/models/fsclvr-fields3 --run out/train-white=data/models/fsclvr-white
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import cached_train_posteriors
from mitsuba_p3.evaluate.metrics import attribute_recovery
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel

ATTRIBUTES = ("shape", "material", "size", "colour")


def score(dataset, run: Path, model: Path, likelihood: str, shots: int | None, only: set[int] | None = None) -> dict:
    """Summary and misreads of one run's cached train posteriors (the first ``shots`` per class; with
    ``only``, of those images only)."""
    cached = {}
    for posteriors in cached_train_posteriors(dataset, run, likelihood).values():
        cached.update({i: p for i, p in sorted(posteriors.items())[:shots] if only is None or i in only})
    if not cached:
        raise SystemExit(f"{run} holds no cached train posteriors for {likelihood}")
    rows, summary = attribute_recovery(dataset, cached, rules_for(FittedModel(model), dataset, learnt=False))
    misread = []
    for r in rows:
        wrong = [f"{a} {r[f'{a}_decided']}" for a in ATTRIBUTES if r[f"{a}_true"] != r[f"{a}_decided"]]
        if wrong:
            misread.append(f"{r['class']}#{r['query']}: " + ", ".join(wrong))
    materials = sorted({r["material_true"] for r in rows if "shape_log_score" in r})
    by_material = {m: round(float(np.mean([r["shape_log_score"] for r in rows
                                           if r["material_true"] == m and "shape_log_score" in r])), 3)
                   for m in materials}
    return {"model": str(model), **{k: round(v, 3) if isinstance(v, float) else v for k, v in summary.items()},
            "shape_log_score_by_material": by_material,
            **gap_summary([p.island_gap for p in cached.values()]), "misread": misread}


def gap_summary(gaps) -> dict:
    """The island gap (the leading hypothesis's runs' log-evidence spread, nats) over the posteriors that
    have one: median, 90th percentile, and how many exceed 10 nats (two runs of one image disagreeing)."""
    gaps = np.asarray([g for g in gaps if np.isfinite(g)], np.float64)
    if not gaps.size:
        return {}
    return {"island_gap_median": round(float(np.median(gaps)), 2),
            "island_gap_p90": round(float(np.percentile(gaps, 90)), 2), "island_gap_over_10": int(np.sum(gaps > 10))}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("--run", action="append", required=True, help="RUN=MODEL (repeatable)")
    parser.add_argument("--likelihood", default="p3")
    parser.add_argument("--shots", type=int, default=None,
                        help="score the first N cached train images per class (default: all cached; give the "
                             "smallest count the runs share, so they score the same images)")
    parser.add_argument("--common", action="store_true",
                        help="score only the images every run has cached (runs still sampling, compared pairwise)")
    args = parser.parse_args()
    dataset = load_dataset(args.dataset)
    runs = run_specs(parser, args.run)
    only = None
    if args.common:
        only = set.intersection(*({i for group in cached_train_posteriors(dataset, run, args.likelihood).values()
                                   for i in group} for run, _ in runs))
    out = {str(run): score(dataset, run, model, args.likelihood, args.shots, only) for run, model in runs}
    print(json.dumps(out, indent=2))


def run_specs(parser: argparse.ArgumentParser, specs: list[str]) -> list[tuple[Path, Path]]:
    """``--run RUN=MODEL`` arguments as (run, model) folders; a malformed one is the parser's error."""
    pairs = []
    for spec in specs:
        run, sep, model = spec.partition("=")
        if not sep:
            parser.error(f"--run takes RUN=MODEL; got {spec!r}")
        pairs.append((Path(run), Path(model)))
    return pairs


if __name__ == "__main__":
    main()
