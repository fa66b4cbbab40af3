"""Every baseline of the paper's table, trained to early stopping and scored, resumable: one command.

For each benchmark of ``--benchmarks`` (default fsclvr, dark, room), each method of
``--methods`` (ProtoNets, first-order MAML) and each input size of ``--resolutions``
(56 and 84 px), meta-trains on the benchmark's train classes until the accuracy on
held-out train classes stops improving (:mod:`mitsuba_p3.baselines.train`; checkpoints
in ``OUT/baselines/V-METHOD-R``), then scores the kept network on the benchmark's test
episodes into ``OUT/runs/V`` (the run folders of ``mitsuba-p3 reproduce``, whose
accuracy table picks them up); the fsclvr networks are also scored on ood
(``OUT/runs/ood``), which has no train classes of its own, as in the paper.

Killed at any point, a rerun resumes: a finished training is not repeated (its
checkpoint says it stopped), an unfinished one continues from its last checkpoint,
and a score already written is kept unless ``--rescore``. The trainings are long on
2 cores (ProtoNets 56 about 2 s per iteration): run it in the background, e.g.

    nohup nice python scripts/train_baselines.py --data data --out results > baselines.log 2>&1 &

Prints one JSON line per finished baseline (iterations, kept iteration, best validation
accuracy, test accuracy per setting) and keeps the benchmark's score in the training folder too
(``scores.json``); ``mitsuba-p3 baseline status OUT/baselines --runs OUT/runs`` tells, in any
session, how far each training got.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path

from mitsuba_p3.baselines.train import (DEFAULT_ITERATIONS, Checkpoint, TrainConfig, evaluate_baseline,
                                        score_file, scored_benchmarks, train_baseline)
from mitsuba_p3.cli.app import progress_bar
from mitsuba_p3.files import atomic_json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--data", type=Path, default=Path("data"), help="folder of the benchmark folders")
    parser.add_argument("--out", type=Path, default=Path("out/reproduction"), help="the reproduction's output folder (reproduce's default)")
    parser.add_argument("--benchmarks", default="fsclvr,dark,room")
    parser.add_argument("--methods", default="protonets,maml")
    parser.add_argument("--resolutions", default="56,84")
    parser.add_argument("--episodes", type=int, default=100, help="test episodes per setting")
    parser.add_argument("--patience", type=int, default=TrainConfig.patience)
    parser.add_argument("--iterations", type=int, default=None, help="cap (default: protonets and maml 20000)")
    parser.add_argument("--rescore", action="store_true", help="score again even where a score exists")
    args = parser.parse_args()

    benchmarks = args.benchmarks.split(",")
    missing = [b for b in benchmarks if not (args.data / b / "labels.json").is_file()]
    if missing:
        raise SystemExit(f"no benchmark folder for {', '.join(missing)} in {args.data} "
                         f"(mitsuba-p3 benchmark generate V --out {args.data}/V)")
    for benchmark in benchmarks:
        for method in args.methods.split(","):
            for resolution in (int(r) for r in args.resolutions.split(",")):
                name = f"{benchmark}-{method}-{resolution}"
                trained = args.out / "baselines" / name
                config = TrainConfig(method=method, resolution=resolution, iterations=args.iterations or DEFAULT_ITERATIONS[method],
                                     patience=args.patience)
                bar, update = progress_bar(name)
                with bar:
                    state = train_baseline(args.data / benchmark, trained, config, progress=update)
                scored = {}
                for target in [t for t in scored_benchmarks(benchmark) if (args.data / t).is_dir()]:
                    result_file = score_file(args.out / "runs" / target, config)
                    if args.rescore or not result_file.exists() or _scored_before(result_file, state):
                        bar, update = progress_bar(f"{name}: scoring on {target}")
                        with bar:
                            evaluate_baseline(trained, args.data / target, args.out / "runs" / target,
                                              args.episodes, progress=update)
                    result = json.loads(result_file.read_text())
                    scored[target] = {k: round(100 * v["mean"], 1) for k, v in result["accuracy"].items()}
                    if target == benchmark:     # the training folder keeps its own score (baseline status reads it)
                        atomic_json(trained / "scores.json", result)
                print(json.dumps({"baseline": name, "iterations": state.iteration, "early_stopped": state.stopped,
                                  "kept_iteration": state.kept_iteration,
                                  "best_validation_accuracy": state.best_validation,
                                  "test_accuracy": scored}), flush=True)


def _scored_before(result_file: Path, state: Checkpoint) -> bool:
    """A score written for an earlier checkpoint than the one training has kept since."""
    return json.loads(result_file.read_text()).get("kept_iteration") != state.kept_iteration


if __name__ == "__main__":
    main()
