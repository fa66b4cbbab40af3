"""Would small objects gain from more pixels? The default SMC at two image sizes, on train images.

A small object covers about 9x9 pixels at 120x160, and a wrong shape free to take its own
pose, size and material comes within about 9 nats of the true one there
(docs/notebook.md). Before building a finer window for small objects into the sampler,
this probe measures what twice the linear resolution would buy.

The fitted world (scene, lights, materials, priors) does not depend on the image size; the
noise model does (pixel sd, outlier weight, correlation area and so the power beta, the
footprint threshold). So the probe fits the noise model of ``--model`` again at
``--resolution``, from the train images of ``--dataset`` (a benchmark generated at that size
or larger; only the train images already rendered are read, so a generation may still be
running), writes
that model to ``--out``, and runs the default SMC on the same evenly spaced train images of
``--size`` at both sizes, side by side: the share with the true shape most probable, the
material (the modal shape's shiny share against the label), the mean log p(true shape) and the
seconds per image. The default window (56x72) is kept at both sizes, so a larger image's small
footprint is scored at the same render cost. No test image is read.

    python experiments/probe_resolution.py --dataset data/room-mid --model data/models/room-lo \\
        --low data/room-lo --resolution 240x320 --out data/models/room-mid --size small --images 16
"""
from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import LABELS_FILE, load_dataset
from mitsuba_p3.files import atomic_json
from mitsuba_p3.fit.model import FittedModel, empty_render, render_train_split
from mitsuba_p3.fit.noise import SPECTRUM_FILE, fit_noise, save_spectra
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.evidence import shape_weights
from mitsuba_p3.infer.smc import SMCConfig, sample_smc


def train_view(root: Path, into: Path) -> Path:
    """A data-set folder holding only ``root``'s rendered train images (its labels filtered, the images copied)."""
    header = json.loads((root / LABELS_FILE).read_text())
    header["images"] = [r for r in header["images"] if r["split"] == "train" and (root / r["file"]).is_file()]
    view = into / root.name
    view.mkdir()
    (view / LABELS_FILE).write_text(json.dumps(header))
    for record in header["images"]:                   # copies: the loader refuses links out of the folder
        (view / record["file"]).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(root / record["file"], view / record["file"])
    for extra in root.iterdir():                      # the scene and anything else beside the labels
        if extra.is_file() and extra.name != LABELS_FILE:
            shutil.copy2(extra, view / extra.name)
    return view


def refit_noise(model_dir: Path, dataset, out: Path) -> FittedModel:
    """A copy of the model with its noise model fitted at ``dataset``'s resolution."""
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(model_dir, out)
    model = FittedModel(out)
    observations, renders = render_train_split(model, dataset, shadows=True)
    noise, figures, spectra = fit_noise(observations, renders,
                                        empty_render(model, *dataset.resolution, shadows=True), shadows=True)
    save_spectra(out / SPECTRUM_FILE, spectra)
    atomic_json(out / "noise.json", {"model": noise.as_dict(), "figures": figures,
                                     "resolution": list(dataset.resolution)})
    return FittedModel(out)


def run(fitted: FittedModel, dataset, shots, config: SMCConfig) -> dict:
    core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise="fitted"), "mitsuba", *dataset.resolution)
    sample_smc(core, core.observe(dataset.image(shots[0])), SMCConfig(particles=4, max_temperatures=2))  # compile
    right, material, log_true, seconds = [], [], [], []
    for shot in shots:
        start = time.perf_counter()
        result = sample_smc(core, core.observe(dataset.image(shot)), config)
        seconds.append(time.perf_counter() - start)
        weights = shape_weights(result.statistics)
        modal = max(weights, key=weights.get)
        right.append(modal == shot.cls.shape)
        material.append((result.statistics["hypotheses"][modal]["shiny"] > 0.5) == (shot.cls.material == "metal"))
        log_true.append(float(np.log(max(weights[shot.cls.shape], 1e-12))))
        print(f"{dataset.resolution} {shot.class_name}/{shot.shot}: {modal} "
              f"({'ok' if right[-1] else 'WRONG'}) {seconds[-1]:.1f} s", flush=True)
    return {"resolution": list(dataset.resolution), "shape": float(np.mean(right)),
            "material": float(np.mean(material)), "log_p_true": float(np.mean(log_true)),
            "seconds": {"median": float(np.median(seconds)), "mean": float(np.mean(seconds))},
            "noise": {k: fitted.noise.as_dict().get(k) for k in ("gaussian_sigma", "power", "footprint")}}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", type=Path, required=True, help="the benchmark at the larger size")
    parser.add_argument("--low", type=Path, required=True, help="the same benchmark at the model's size")
    parser.add_argument("--model", type=Path, required=True, help="the model fitted at the smaller size")
    parser.add_argument("--resolution", default="240x320", help="HxW of the finer run")
    parser.add_argument("--out", type=Path, required=True, help="model folder to write (the noise refitted)")
    parser.add_argument("--size", choices=("small", "large"), default="small")
    parser.add_argument("--images", type=int, default=16)
    args = parser.parse_args()

    height, width = (int(v) for v in args.resolution.lower().split("x"))
    with tempfile.TemporaryDirectory() as tmp:
        fine = load_dataset(train_view(args.dataset, Path(tmp)), resolution=(height, width))
        low = load_dataset(args.low)
        model = refit_noise(args.model, fine, args.out)
        fine_shots = [s for s in fine.split("train") if s.cls.size == args.size]
        if not fine_shots:
            raise SystemExit(f"{args.dataset} has no {args.size} train image rendered yet")
        chosen = np.linspace(0, len(fine_shots) - 1, min(args.images, len(fine_shots))).astype(int)
        fine_shots = [fine_shots[i] for i in chosen]
        same = {(s.class_name, s.shot): s for s in low.split("train")}
        if any((s.class_name, s.shot) not in same for s in fine_shots):
            raise SystemExit("the two data sets do not hold the same train images (same variant and seed?)")
        low_shots = [same[s.class_name, s.shot] for s in fine_shots]
        config = SMCConfig()
        report = {"images": len(chosen), "size": args.size,
                  "low": run(FittedModel(args.model), low, low_shots, config),
                  "fine": run(model, fine, fine_shots, config)}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
