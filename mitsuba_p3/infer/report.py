"""Write a posterior and the figures a person looks at into a folder."""
from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .. import plots
from ..files import atomic_json
from ..fit.attributes import AttributeRules, rules_for
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


def read_material_rule(fitted: FittedModel, path: str | Path) -> AttributeRules:
    """The fit's attribute rules with the material rule saved at ``path`` (``mitsuba-p3 evaluate`` writes
    ``RUN/material-rule-LIKELIHOOD.json``, learnt from its train posteriors). A rule that reads the
    Phong misfit needs the model's fitted noise model, the misfit's unit."""
    from ..errors import ConfigError

    try:
        rules = rules_for(fitted).with_material_record(json.loads(Path(path).read_text()))
    except (OSError, ValueError) as error:
        raise ConfigError(f"{path}: {error}") from None
    if rules.reads_misfit and not (fitted.root / "noise.json").exists():
        raise ConfigError(f"{path} reads the Phong misfit, which needs {fitted.root}'s noise stage; run "
                          f"mitsuba-p3 fit DATASET --out {fitted.root} --stages noise")
    return rules


def posterior_misfit(posterior: Posterior, fitted: FittedModel, observed: np.ndarray) -> float:
    """The Phong misfit (:func:`~mitsuba_p3.infer.misfit.phong_misfit`) at the posterior's pose estimate."""
    from .misfit import model_misfit

    estimate = posterior.estimate()
    pose = {"shift": np.asarray(estimate["shift"], np.float64), "theta": float(estimate["theta"]),
            "scale": np.median(posterior.draws("scale").reshape(-1, 3), axis=0), "kappa": int(estimate["kappa"])}
    return model_misfit(fitted, observed, pose)


# a posterior median half-extent further than this many prior standard deviations (of log size) from the
# prior's centre is outside the model's range (3.29: the prior's central 99.9%)
RANGE_SIGMAS = 3.29


def lost_hypotheses(posterior: Posterior) -> list[str]:
    """The hypotheses every one of whose SMC runs lost the object (:func:`~mitsuba_p3.infer.evidence.mark_lost_runs`)."""
    hypotheses = posterior.statistic("hypotheses") or {}
    return [name for name, h in hypotheses.items()
            if isinstance(h, dict) and h.get("runs") and h.get("lost_runs", 0) >= h["runs"]]


def range_warnings(posterior: Posterior, fitted: FittedModel, diagnostics: dict) -> list[str]:
    """What says the answer is about something the model cannot explain: the empty floor explains the
    image better than one object (an SMC posterior's log Bayes factor < 0), or the object's size lies
    outside the prior's central 99.9%. Empty when the answer is within the model."""
    warnings = []
    factor = diagnostics.get("log_bayes_factor_object")
    if factor is not None and np.isfinite(factor) and factor < 0:
        warnings.append(f"the empty floor explains this image better than one object (log Bayes factor "
                        f"{factor:.1f}): there may be no object here")
    lost = diagnostics.get("lost_hypotheses") or []
    if lost:
        warnings.append(f"every run of {', '.join(lost)} explained the image hardly better than the empty floor "
                        "(it lost the object): its weight says nothing about that shape; sample again with more "
                        "particles or another seed")
    config = fitted.prior.config
    size = np.median(posterior.draws("scale").reshape(-1, 3), axis=0)
    far = np.abs(np.log(size) - config.scale_log_mu) / config.scale_log_sigma
    if np.any(far > RANGE_SIGMAS):
        warnings.append(f"the object's size ({', '.join(f'{v * 1000:.0f}' for v in size)} mm half-extents) lies "
                        f"outside the range the model was fitted on (the prior's central 99.9%, "
                        f"{1000 * np.exp(config.scale_log_mu - RANGE_SIGMAS * config.scale_log_sigma):.0f}-"
                        f"{1000 * np.exp(config.scale_log_mu + RANGE_SIGMAS * config.scale_log_sigma):.0f} mm)")
    return warnings


def write_report(posterior: Posterior, fitted: FittedModel, out: str | Path, renderer: str = "mitsuba",
                 samples: int = 6, truth: dict | None = None, rules: AttributeRules | None = None) -> dict[str, str]:
    """posterior.nc, summary.csv, estimate.json and the figures; returns what was written. The
    attributes are named by ``rules`` (:func:`read_material_rule`), or by the fit's."""
    from ..render import make_renderer

    out = Path(out)
    out.mkdir(parents=True, exist_ok=True)
    written = {"posterior": str(posterior.save(out / "posterior.nc"))}
    summary = posterior.summary()
    summary.to_csv(out / "summary.csv")
    written["summary"] = str(out / "summary.csv")
    estimate = posterior.estimate()
    if posterior.sampler == "smc":
        # one pool of resampled draws: no R-hat; the independent runs' agreement instead
        diagnostics = {"island_gap": posterior.statistic("island_gap"),
                       "temperatures": posterior.statistic("temperatures"),
                       "forced": posterior.statistic("forced"),
                       # one object against the empty floor (evidence.object_evidence): < 0, nothing explained
                       "log_bayes_factor_object": posterior.statistic("log_bayes_factor_object"),
                       "lost_hypotheses": lost_hypotheses(posterior)}
    else:
        diagnostics = {"max_r_hat": float(summary["r_hat"].max()), "min_ess_bulk": float(summary["ess_bulk"].min())}
    attrs = dict(posterior.idata.posterior.attrs)
    estimate_file = out / "estimate.json"
    draws = {name: posterior.draws(name) for name in ("scale", "colour", "ambient", "diffuse", "specular", "shininess")}
    observed = np.asarray(posterior.idata.observed_data["image"].values, np.float32)
    rules = rules or rules_for(fitted)
    misfit = posterior_misfit(posterior, fitted, observed) if rules.reads_misfit else None
    attributes = {**rules.decide({**draws, "class": posterior.draws("kappa")}, misfit),
                  "material_rule": rules.material_features if rules.material_model is not None else "one kind",
                  **({"misfit": misfit} if misfit is not None else {})}
    from ..files import file_digest

    warnings = range_warnings(posterior, fitted, diagnostics)

    # what the answer depends on: the model's files as they were read (a refit changes model.json)
    provenance = {"model": str(Path(fitted.root).resolve()), "model_digest": file_digest(Path(fitted.root) / "model.json"),
                  **({"image": attrs["image"], "image_digest": file_digest(attrs["image"])}
                     if attrs.get("image") and Path(str(attrs["image"])).is_file() else {})}
    atomic_json(estimate_file, {"estimate": estimate, "attributes": attributes, "diagnostics": diagnostics,
                                "seconds": attrs.get("seconds"), "acceptance": attrs.get("acceptance"),
                                "provenance": provenance, "warnings": warnings})
    written["estimate"] = str(estimate_file)

    height, width = observed.shape[:2]
    # the renders the likelihood compared: with hard shadows when its noise model had them
    noise = attrs.get("noise", "{}")
    shadows = bool((json.loads(noise) if isinstance(noise, str) else noise).get("shadows", False))
    render = make_renderer(fitted.scene(), renderer, height=height, width=width, shadows=shadows)
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
    if posterior.sampler == "smc":
        written["figure_runs"] = str(plots.island_evidence(posterior.statistic("hypotheses"), out / "runs.png",
                                                           posterior.statistic("steps")))
    else:
        written["figure_trace"] = str(plots.trace_plot(posterior.idata, out / "trace.png"))
    return written
