"""Posteriors of the first N images of every train class, for choices scored on K-shot train episodes.

``mitsuba-p3 evaluate`` samples three train images per class (the concept spread's). A
5-shot episode needs six images of a class (five supports and a query), so a choice that
must hold in the 5-shot settings is scored on runs made with this script, then with

    python experiments/select_spread.py DATASET RUN --shots 1,5

The run folder is an evaluation run (same ``run.json``, same cache): posteriors already in
it are kept, a killed run resumes, and ``mitsuba-p3 evaluate`` can later use it. ``--sampler``
sets :class:`~mitsuba_p3.infer.smc.SMCConfig` fields (JSON), e.g. ``'{"ridge": 0}'``.

    python experiments/sample_train_shots.py data/fsclvr-lo data/models/fsclvr-lo RUN --shots 6 --jobs 2
"""
from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from mitsuba_p3.concepts import DistanceConfig
from mitsuba_p3.errors import MitsubaP3Error
from mitsuba_p3.evaluate.config import EvaluationConfig
from mitsuba_p3.evaluate.run import sample_spread
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.smc import SMCConfig


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset", type=Path)
    parser.add_argument("model", type=Path)
    parser.add_argument("run", type=Path, help="run folder (resumes; an evaluation run with the same settings)")
    parser.add_argument("--shots", type=int, default=6, help="train images per class")
    parser.add_argument("--sampler", default="{}", help="JSON: SMCConfig fields that differ from the default")
    parser.add_argument("--noise", default=DEFAULT_NOISE, help=f"the likelihood (default {DEFAULT_NOISE}, as evaluate's)")
    parser.add_argument("--jobs", type=int, default=1)
    args = parser.parse_args()
    try:
        config = EvaluationConfig(likelihoods=("p3",), noise=args.noise, jobs=args.jobs,
                                  sampler=SMCConfig(**json.loads(args.sampler)),
                                  distance=DistanceConfig(spread_shots=args.shots))
        sample_spread(args.dataset, args.model, args.run, config,
                      lambda what, done, total: print(f"{what}: {done}/{total}", file=sys.stderr, flush=True))
    except (MitsubaP3Error, TypeError, ValueError) as error:
        parser.error(str(error))


if __name__ == "__main__":
    main()
