"""Write a posterior and the figures a person looks at into a folder."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import plots
from ..files import atomic_json
from ..fit.attributes import rules_for
from ..fit.model import FittedModel
from ..space import render_params
from .posterior import Posterior


def estimate_params(estimate: dict) -> dict[str, np.ndarray]:
    """The renderer contract's object parameters of a point estimate."""
    one_hot = np.eye(len(estimate["class_frequencies"]))[estimate["kappa"]]
    return render_params({**estimate, "class_probabilities": one_hot})


def draw_params(posterior: Posterior, indices: np.ndarray) -> dict[str, np.ndarray]:
    """Contract parameters of some posterior draws (batched)."""
    names = ("shift", "theta", "scale", "class_probabilities", "colour", "ambient", "diffuse", "specular",
             "shininess")
    return render_params({name: posterior.draws(name)[indices] for name in names})


def write_report(posterior: Posterior, fitted: FittedModel, out: str | Path, renderer: str = "mitsuba",
                 samples: int = 6, truth: dict | None = None) -> dict[str, str]:
    """posterior.nc, summary.csv, estimate.json and the figures; returns what was written."""
    from ..render import make_renderer

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = {"posterior": str(posterior.save(out / "posterior.nc"))}
    summary = posterior.summary()
    summary.to_csv(out / "summary.csv")
    written["summary"] = str(out / "summary.csv")
    estimate = posterior.estimate()
    diagnostics = {"max_r_hat": float(summary["r_hat"].max()), "min_ess_bulk": float(summary["ess_bulk"].min())}
    attrs = dict(posterior.idata.posterior.attrs)
    estimate_file = out / "estimate.json"
    draws = {name: posterior.draws(name) for name in ("scale", "colour", "ambient", "diffuse", "specular", "shininess")}
    attributes = rules_for(fitted).decide({**draws, "class": posterior.draws("kappa")})
    atomic_json(estimate_file, {"estimate": estimate, "attributes": attributes, "diagnostics": diagnostics,
                                "seconds": attrs.get("seconds"), "acceptance": attrs.get("acceptance")})
    written["estimate"] = str(estimate_file)

    observed = np.asarray(posterior.idata.observed_data["image"].values, np.float32)
    height, width = observed.shape[:2]
    # the renders the likelihood compared: with hard shadows when its noise model had them
    noise = attrs.get("noise", "{}")
    shadows = bool((json.loads(noise) if isinstance(noise, str) else noise).get("shadows", False))
    render = make_renderer(fitted.scene(), "mitsuba", height=height, width=width, shadows=shadows)
    rng = np.random.default_rng(0)
    indices = rng.choice(len(posterior.draws("theta")), size=samples, replace=False)
    estimate_render = render.render(estimate_params(estimate))
    written["figure_renders"] = str(plots.posterior_renders(
        observed, estimate_render, render.render(draw_params(posterior, indices)), out / "posterior.png",
        f"{estimate['shape']} (p = {estimate['class_frequencies'][estimate['shape']]:.2f})",
        box=plots.object_box(estimate_render, render.render_empty())))
    written["figure_translation"] = str(plots.translation_contours(
        posterior.draws("shift"), out / "translation.png", truth=(truth or {}).get("shift")))
    written["figure_colour"] = str(plots.colour_posterior(posterior.draws("colour"), out / "colour.png",
                                                          truth=(truth or {}).get("colour")))
    written["figure_trace"] = str(plots.trace_plot(posterior.idata, out / "trace.png"))
    return written
