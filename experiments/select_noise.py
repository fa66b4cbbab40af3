"""Choose the likelihood's noise form on train classes: which one lets the sampler find the object.

The fit stage fits two noise models to the train residuals (:mod:`mitsuba_p3.fit.noise`):
a Gaussian (sigma = the residuals' RMS) and an inlier/outlier mixture. Both describe
the residuals at the true geometry; the question for inference is which one ranks
*hypotheses* right. For evenly spaced images of the train split (the classes the
model was fitted on; the test split is never read), this samples the P3 posterior
with tempered SMC (:mod:`mitsuba_p3.infer.smc`) under each form and prints JSON:
the share of images whose most probable shape, and whose posterior-mean size
class, match the labels, the mean log p(true shape), the mean position error of the
posterior-mean shift, the SMC's temperatures, and seconds per image.

    python experiments/select_noise.py --dataset data/fsclvr --model data/models/fsclvr [--images 30]
        [--forms fitted,robust,spectral] [--particles 32] [--islands 1] [--out rows.jsonl]
        [--shrink 0,1,3 --copies DIR] [--models phong=data/models/fsclvr,ggx=data/models/fsclvr-ggx]

``--models`` compares fitted models (e.g. two observation models, ``fit --observation``) on the
same images: each model is scored under each form, and rows are named ``MODEL/FORM``.

``--shrink`` adds one spectral form per lambda (the spectrum's shrinkage towards white noise,
:mod:`mitsuba_p3.fit.noise`): the model's noise stage is fitted again with that lambda into a
copy of the model under ``--copies`` (the train split only), and named ``spectral-LAMBDA``.

With ``--out`` every image's row is appended to a JSON-lines file as it is done, and a
rerun skips the (form, image) pairs already there: a killed run loses one image.
"""
from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.attributes import rules_for
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.infer.evidence import shape_weights
from mitsuba_p3.infer.smc import SMCConfig, sample_smc


def size_class(scale: np.ndarray, sizes: dict[str, float]) -> str:
    """The size name whose half-extent is nearest in log to the posterior mean's (geometric) half-extent."""
    value = float(np.exp(np.mean(np.log(scale))))
    return min(sizes, key=lambda name: abs(np.log(sizes[name]) - np.log(value)))


_TRAIN = {}


def shrunk_model(model_dir: Path, dataset, shrink: float, out: Path) -> FittedModel:
    """A copy of the model whose noise stage is fitted again with spectral shrinkage ``shrink``."""
    import shutil

    from mitsuba_p3.files import atomic_json
    from mitsuba_p3.fit.model import empty_render, render_train_split
    from mitsuba_p3.fit.noise import SPECTRUM_FILE, fit_noise, save_spectra

    if (out / "noise.json").is_file() and json.loads((out / "noise.json").read_text())["model"].get(
            "spectral_shrink") == shrink:
        return FittedModel(out)
    if out.exists():
        shutil.rmtree(out)
    shutil.copytree(model_dir, out)
    model = FittedModel(out)
    if "pairs" not in _TRAIN:
        _TRAIN["pairs"] = render_train_split(model, dataset, shadows=True)
        _TRAIN["empty"] = empty_render(model, *dataset.resolution, shadows=True)
    noise, figures, spectra = fit_noise(*_TRAIN["pairs"], _TRAIN["empty"], shadows=True, spectral_shrink=shrink)
    save_spectra(out / SPECTRUM_FILE, spectra)
    atomic_json(out / "noise.json", {"model": noise.as_dict(), "figures": figures})
    print(f"spectral-{shrink}: power {noise.spectral_power:.4g}, {figures['spectral']}", flush=True)
    return FittedModel(out)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dataset", default="data/fsclvr")
    parser.add_argument("--model", default="data/models/fsclvr")
    parser.add_argument("--images", type=int, default=30, help="evenly spaced train images")
    parser.add_argument("--forms", default="fitted,robust")
    parser.add_argument("--particles", type=int, default=SMCConfig.particles)
    parser.add_argument("--islands", type=int, default=SMCConfig.islands, help="independent SMC runs, pooled")
    parser.add_argument("--out", type=Path, help="JSON-lines file of per-image rows (appended; resumes)")
    parser.add_argument("--shrink", default="", help="lambdas of spectral forms fitted again (comma-separated)")
    parser.add_argument("--copies", type=Path, default=Path("out/select-noise-models"))
    parser.add_argument("--models", default="", help="NAME=MODEL_DIR pairs to compare (comma-separated); "
                                                     "default: --model alone")
    args = parser.parse_args()
    done = {}
    if args.out and args.out.is_file():
        for line in args.out.read_text().splitlines():
            row = json.loads(line)
            done[row["form"], row["index"]] = row

    dataset = load_dataset(args.dataset)
    fitted = FittedModel(args.model)
    shots = dataset.split("train")
    shots = [shots[i] for i in np.linspace(0, len(shots) - 1, min(args.images, len(shots))).astype(int)]
    # the train labels' half-extents per size name (the size rule of the attributes, learnt on train)
    sizes = {}
    for shot in dataset.split("train"):
        sizes.setdefault(shot.cls.size, []).append(float(np.exp(np.mean(np.log(shot.scale)))))
    sizes = {name: float(np.median(v)) for name, v in sizes.items()}
    config = SMCConfig(particles=args.particles, islands=args.islands)
    report = {"dataset": args.dataset, "images": len(shots),
              "smc": {"particles": config.particles, "islands": config.islands}}
    forms = [f.strip() for f in args.forms.split(",") if f.strip()]
    models = {form: fitted for form in forms}
    if args.models:
        pairs = [item.split("=", 1) for item in args.models.split(",") if item.strip()]
        models = {f"{name}/{form}": FittedModel(path) for name, path in pairs for form in forms}
    for value in [v.strip() for v in args.shrink.split(",") if v.strip()]:
        models[f"spectral-{value}"] = shrunk_model(args.model, dataset, float(value), args.copies / f"shrink-{value}")
    # images outside, forms inside: a run stopped early compares the forms on the same images
    cores, rows = {}, {form: [] for form in models}
    rules = {form: rules_for(model, dataset, learnt=False) for form, model in models.items()}
    for i, shot in enumerate(shots):
        for form, model in models.items():
            if (form, shot.index) in done:
                rows[form].append(done[form, shot.index])
                continue
            if form not in cores:
                noise = form.split("/")[-1].split("-")[0]
                cores[form] = PosteriorCore(model, default_likelihood(model, "p3", noise=noise), "mitsuba",
                                            *dataset.resolution)
            core = cores[form]
            start = time.perf_counter()
            run = sample_smc(core, core.observe(dataset.image(shot)), config)
            seconds = time.perf_counter() - start
            weights = shape_weights(run.statistics)
            scale = np.exp(run.positions[..., 3:6].reshape(-1, 3)).mean(axis=0)
            drawn = {k: np.asarray(v) for k, v in
                     core.prior.constrain(run.positions.reshape(-1, run.positions.shape[-1])).items()}
            shift = drawn["shift"]
            drawn["class"] = np.argmax(drawn.pop("class_probabilities"), axis=-1)
            rule = rules[form].decide(drawn)
            row = {"form": form, "index": shot.index, "class": shot.class_name,
                   "shape_right": max(weights, key=weights.get) == shot.cls.shape,
                   "size_right": size_class(scale, sizes) == shot.cls.size,
                   "log_p_true_shape": float(np.log(max(weights[shot.cls.shape], 1e-12))),
                   "position_error_mm": 1000 * float(np.linalg.norm(shift.mean(axis=0) - shot.position[:2])),
                   # p(shiny): the specular weight above the prior's threshold (the SMC's statistic), a
                   # proxy of the material kind (the attributes' rule also weighs the Phong misfit)
                   "material_right": bool((sum(h["weight"] * h["shiny"] for h in run.statistics["hypotheses"].values())
                                           > 0.5) == (shot.cls.material == "metal")),
                   # the fit's own material rule (a logistic regression on the fitted train materials)
                   "material_rule_right": rule["material"] == shot.cls.material,
                   "temperatures": int(run.statistics["temperatures"]), "forced": run.statistics["forced"],
                   "seconds": seconds}
            rows[form].append(row)
            if args.out:
                with open(args.out, "a") as f:
                    f.write(json.dumps(row) + "\n")
            print(f"{form} {i + 1}/{len(shots)} {shot.class_name}: shape {'ok' if row['shape_right'] else 'WRONG'} "
                  f"size {'ok' if row['size_right'] else 'WRONG'} {row['position_error_mm']:.1f} mm "
                  f"T={row['temperatures']} {seconds:.1f} s", flush=True)
    for form, done_rows in rows.items():
        report[form] = {"shape": float(np.mean([r["shape_right"] for r in done_rows])),
                        "size": float(np.mean([r["size_right"] for r in done_rows])),
                        "mean_log_p_true_shape": float(np.mean([r["log_p_true_shape"] for r in done_rows])),
                        "material_kind_p_shiny": float(np.mean([r["material_right"] for r in done_rows
                                                                if "material_right" in r] or [np.nan])),
                        "material_kind_fit_rule": float(np.mean([r["material_rule_right"] for r in done_rows
                                                                 if "material_rule_right" in r] or [np.nan])),
                        "mean_position_error_mm": float(np.mean([r["position_error_mm"] for r in done_rows])),
                        "median_temperatures": float(np.median([r["temperatures"] for r in done_rows])),
                        "forced": float(np.mean([r["forced"] for r in done_rows])),
                        "seconds_per_image": float(np.median([r["seconds"] for r in done_rows]))}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
