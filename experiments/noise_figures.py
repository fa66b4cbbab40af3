"""The fit's noise figures of fitted models, side by side: how far each world's images are from the
Phong model (residual RMS, correlation area, the power and effective sigma it gives) and what the
shading fields leave (their sigma, power and correlation area after the fields).

    python experiments/noise_figures.py fsclvr-lo=data/models/fsclvr-lo jitter-lo=data/models/jitter-lo \\
        --out results/worlds/noise-figures.json

Reads each model's ``noise.json`` and ``model.json``; renders nothing.
"""
from __future__ import annotations

import argparse
import json
from pathlib import Path


def figures_of(model: Path) -> dict:
    """One model's figures (the module docstring)."""
    noise = json.loads((model / "noise.json").read_text())
    stages = json.loads((model / "model.json").read_text())["stages"]
    figures, fields = noise["figures"], noise["figures"].get("fields") or {}
    return {"residual_rms": figures["residual_rms"], "correlation_area_pixels": figures["correlation_area_pixels"],
            "power": noise["model"]["power"], "effective_sigma": figures["effective_sigma"],
            "footprint_threshold": noise["model"]["footprint"],
            "fields_regions": len(fields["taus"]) // (fields["degree"] + 1) if fields else None,
            "fields_sigma": fields.get("sigma"), "fields_power": fields.get("power"),
            "fields_area_window": fields.get("correlation_area_window"),
            "fields_area_after": fields.get("correlation_area_after_fields"),
            "scene_fit_mse": stages["scene"]["final_mean_squared_error"]}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("models", nargs="+", help="NAME=MODEL_FOLDER")
    parser.add_argument("--out", type=Path, help="also write the figures here (JSON)")
    args = parser.parse_args()
    table = {}
    for item in args.models:
        name, _, folder = item.partition("=")
        if not folder:
            parser.error(f"{item!r}: give NAME=MODEL_FOLDER")
        table[name] = figures_of(Path(folder))
    print(f"{'model':14s} {'RMS':>7s} {'area':>6s} {'eff. sigma':>10s} {'fields: regions':>15s} {'area after':>10s} "
          f"{'power':>7s}")
    for name, f in table.items():
        after = "-" if f["fields_area_after"] is None else f"{f['fields_area_after']:.1f}"
        power = "-" if f["fields_power"] is None else f"{f['fields_power']:.4f}"
        print(f"{name:14s} {f['residual_rms']:7.4f} {f['correlation_area_pixels']:6.1f} {f['effective_sigma']:10.3f} "
              f"{f['fields_regions'] or '-':>15} {after:>10s} {power:>7s}")
    if args.out:
        args.out.write_text(json.dumps(table, indent=1) + "\n")


if __name__ == "__main__":
    main()
