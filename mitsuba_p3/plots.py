"""Figures a person looks at: contact sheets and image grids (matplotlib, no display needed)."""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import numpy as np


def _pyplot():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig, path: str | Path, dpi: int = 110) -> Path:
    """Save a figure atomically (a killed run never leaves half a PNG) and close it."""
    plt = _pyplot()
    from .files import atomic_path

    path = Path(path)
    try:
        with atomic_path(path) as temporary:
            fig.savefig(temporary, dpi=dpi, bbox_inches="tight")
    finally:
        plt.close(fig)
    return path


def image_grid(images: Sequence[np.ndarray], titles: Sequence[str], path: str | Path,
               columns: int = 6, title: str | None = None, cell: float = 2.0) -> Path:
    """Images in a grid, each with a small title underneath."""
    plt = _pyplot()
    rows = max(1, -(-len(images) // columns))
    aspect = images[0].shape[0] / images[0].shape[1] if images else 0.75
    fig, axes = plt.subplots(rows, columns, figsize=(cell * columns, cell * aspect * rows + 0.35 * rows + 0.4),
                             squeeze=False)
    for ax in axes.flat:
        ax.axis("off")
    for ax, image, text in zip(axes.flat, images, titles):
        ax.imshow(np.clip(image, 0, 1), interpolation="nearest")
        ax.set_title(text, fontsize=7, y=-0.16)
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def contact_sheet(dataset, path: str | Path, columns: int = 8) -> Path:
    """One labelled shot (shot 0) per class of a data set, train classes first."""
    images, titles = [], []
    for split in ("train", "test"):
        for name in dataset.classes(split):
            shot = dataset.shots_of(name)[0]
            images.append(dataset.image(shot))
            titles.append(f"{split}: {name}")
    title = f"{dataset.variant}: {len(titles)} classes ({dataset.root})"
    return image_grid(images, titles, path, columns=min(columns, len(images)), title=title)


# ---------------------------------------------------------------- training-stage figures
def optimisation_progress(snapshots: dict, path: str | Path, title: str = "") -> Path:
    """Rows: training images; columns: the observation, then the render after each epoch."""
    plt = _pyplot()
    observations, renders = snapshots["observations"], snapshots["renders"]
    epochs = renders.shape[0]
    columns = [0] + sorted(set(np.linspace(1, epochs - 1, min(4, epochs - 1)).astype(int).tolist()))
    rows = len(observations)
    fig, axes = plt.subplots(rows, len(columns) + 1, figsize=(2.2 * (len(columns) + 1), 1.75 * rows + 0.5),
                             squeeze=False)
    for r in range(rows):
        axes[r, 0].imshow(np.clip(observations[r], 0, 1))
        axes[r, 0].set_title("observation" if r == 0 else "", fontsize=8)
        for c, epoch in enumerate(columns, start=1):
            axes[r, c].imshow(np.clip(renders[epoch, r], 0, 1))
            if r == 0:
                axes[r, c].set_title("initial" if epoch == 0 else f"epoch {epoch}", fontsize=8)
    for ax in axes.flat:
        ax.axis("off")
    fig.suptitle(title or "scene optimisation", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def loss_curve(rows: list[dict], path: str | Path, title: str = "") -> Path:
    """Mean L2 loss per pass, material and global passes coloured apart."""
    plt = _pyplot()
    fig, ax = plt.subplots(figsize=(6, 3))
    x = np.arange(len(rows))
    losses = np.array([float(r["loss"]) for r in rows])
    for phase, colour in (("materials", "tab:orange"), ("globals", "tab:blue")):
        mask = np.array([r["phase"] == phase for r in rows])
        ax.scatter(x[mask], losses[mask], s=10, color=colour, label=f"{phase} pass")
    ax.plot(x, losses, color="0.6", lw=0.8, zorder=0)
    ax.set_yscale("log")
    ax.set_xlabel("pass")
    ax.set_ylabel("mean squared error")
    ax.legend(fontsize=8)
    ax.set_title(title or "scene optimisation loss", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def gmm_priors(prior, materials: dict, path: str | Path) -> Path:
    """Each GMM prior's density over the fitted materials it was fitted to (a rug and a histogram)."""
    from .space import MATERIAL_VARIABLES

    plt = _pyplot()
    panels = [("colour", i, name) for i, name in enumerate(("red", "green", "blue"))] + \
             [(v, 0, v) for v in MATERIAL_VARIABLES if v != "colour"]
    fig, axes = plt.subplots(2, 4, figsize=(12, 5))
    for ax, (variable, dim, label) in zip(axes.flat, panels):
        g = prior.gmms[variable]
        values = np.array([np.atleast_1d(m[variable])[dim] for m in materials.values()])
        lo, hi = min(values.min(), (g.means[:, dim] - 3 * np.sqrt(g.variances[:, dim])).min()), \
            max(values.max(), (g.means[:, dim] + 3 * np.sqrt(g.variances[:, dim])).max())
        grid = np.linspace(lo, hi, 400)
        density = sum(w * np.exp(-0.5 * (grid - m) ** 2 / v) / np.sqrt(2 * np.pi * v)
                      for w, m, v in zip(g.weights, g.means[:, dim], g.variances[:, dim]))
        ax.hist(values, bins=12, density=True, color="0.8", label="fitted materials")
        ax.plot(grid, density, color="tab:red", label="GMM prior (marginal)")
        ax.plot(values, np.zeros_like(values), "|", color="k", ms=12)
        ax.set_title(label, fontsize=9)
    axes.flat[-1].axis("off")
    axes.flat[0].legend(fontsize=7)
    fig.suptitle("GMM priors over the optimised materials", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def reparametrisation(prior, path: str | Path, samples: int = 20000, seed: int = 0) -> Path:
    """For each variable: prior samples in the natural space and in the unconstrained space,
    with the pushed-back density log p(z) drawn over the latter."""
    from .space import SLICES

    plt = _pyplot()
    rng = np.random.default_rng(seed)
    x = prior.sample_constrained(rng, samples)
    z = prior.unconstrain(x)
    panels = [("shift", 0, "shift x (m)"), ("theta", None, "theta (rad)"), ("scale", 0, "scale x (m)"),
              ("class_probabilities", 0, "class: P(sphere)"), ("colour", 0, "colour red"),
              ("ambient", None, "ambient"), ("diffuse", None, "diffuse"), ("specular", None, "specular"),
              ("shininess", None, "shininess")]
    zkey = {"class_probabilities": "kappa"}
    fig, axes = plt.subplots(2, len(panels), figsize=(2.1 * len(panels), 4.4))
    for c, (name, dim, label) in enumerate(panels):
        values = x[name] if dim is None else x[name][:, dim]
        axes[0, c].hist(values, bins=60, density=True, color="tab:blue", alpha=0.7)
        axes[0, c].set_title(label, fontsize=8)
        column = SLICES[zkey.get(name, name)].start + (dim or 0)
        axes[1, c].hist(z[:, column], bins=60, density=True, color="tab:green", alpha=0.7)
        if name in ("theta", "ambient", "diffuse", "specular", "shininess"):
            grid = np.linspace(*np.percentile(z[:, column], [0.5, 99.5]), 300)
            zz = np.zeros((len(grid), z.shape[1]))
            zz[:, column] = grid
            part = name
            axes[1, c].plot(grid, np.exp(np.asarray(prior.log_prob_parts(zz)[part])), color="k", lw=1)
        axes[1, c].set_xlabel("unconstrained z", fontsize=7)
        for ax in axes[:, c]:
            ax.tick_params(labelsize=6)
    axes[0, 0].set_ylabel("natural space", fontsize=8)
    axes[1, 0].set_ylabel("unconstrained", fontsize=8)
    fig.suptitle("reparametrisation: prior samples before and after the bijectors (black: p(z))", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


# ---------------------------------------------------------------- inference figures
def posterior_renders(observed: np.ndarray, estimate_render: np.ndarray, samples: np.ndarray,
                      path: str | Path, title: str = "", box: tuple[int, int, int, int] | None = None) -> Path:
    """The observation, the render of the point estimate, and renders of posterior draws. With
    ``box`` (top, left, height, width) every panel but a first whole observation shows that crop,
    so a small object fills the panel."""
    images = [observed, estimate_render] + list(samples)
    titles = ["observation", "point estimate"] + [f"posterior draw {i + 1}" for i in range(len(samples))]
    if box is not None:
        top, left, height, width = box
        images = [observed] + [image[top:top + height, left:left + width] for image in images]
        titles = ["observation (whole)"] + [f"{t} (zoomed)" for t in titles]
    return image_grid(images, titles, path, columns=min(4, len(images)), title=title or "posterior")


def object_box(estimate_render: np.ndarray, empty_render: np.ndarray, context: float = 2.0,
               threshold: float = 0.02) -> tuple[int, int, int, int] | None:
    """A box (top, left, height, width) with the image's aspect around where a render differs from the
    empty floor's (object and shadow), ``context`` times that region's size and at least a quarter of
    the image's height; None when the render does not differ or the box would be most of the image."""
    rows, cols = np.nonzero(np.max(np.abs(np.asarray(estimate_render) - np.asarray(empty_render)), axis=-1) > threshold)
    image_h, image_w = estimate_render.shape[:2]
    if rows.size == 0:
        return None
    aspect = image_w / image_h
    height = max(context * (np.ptp(rows) + 1), context * (np.ptp(cols) + 1) / aspect, image_h / 4)
    height, width = int(round(height)), int(round(height * aspect))
    if height >= 0.75 * image_h:
        return None
    top = int(np.clip((rows.min() + rows.max() + 1 - height) // 2, 0, image_h - height))
    left = int(np.clip((cols.min() + cols.max() + 1 - width) // 2, 0, image_w - width))
    return top, left, height, width


def hdi_levels(density: np.ndarray, masses: Sequence[float]) -> list[float]:
    """Density thresholds whose super-level sets hold the given probability masses."""
    values = np.sort(density.ravel())[::-1]
    cumulative = np.cumsum(values) / values.sum()
    return [float(values[min(np.searchsorted(cumulative, m), len(values) - 1)]) for m in masses]


def translation_contours(shift: np.ndarray, path: str | Path, truth: Sequence[float] | None = None,
                         masses: Sequence[float] = (0.05, 0.2, 0.4, 0.6, 0.8)) -> Path:
    """Posterior of the floor position: KDE contours enclosing 5-80% of the mass (HDI regions)."""
    from scipy.stats import gaussian_kde

    plt = _pyplot()
    shift = np.asarray(shift)[:: max(1, len(shift) // 5000)]
    # draws that barely move (short chains, a sharp posterior) have a singular covariance: jitter them
    # by 0.1 mm so the KDE exists; the contours then mark where the draws sit
    if len(shift) < 3 or np.linalg.eigvalsh(np.cov(shift.T)).min() < 1e-12:
        base = np.resize(shift, (max(len(shift), 3), 2))
        shift = base + np.random.default_rng(0).normal(0.0, 1e-4, base.shape)
    kde = gaussian_kde(shift.T)
    centre = (shift.min(0) + shift.max(0)) / 2
    half = 0.625 * max(float(np.max(shift.max(0) - shift.min(0))), 2e-3)  # a square window, 25% margin
    x, y = np.meshgrid(np.linspace(centre[0] - half, centre[0] + half, 120),
                       np.linspace(centre[1] - half, centre[1] + half, 120))
    density = kde(np.vstack([x.ravel(), y.ravel()])).reshape(x.shape)
    levels = sorted(set(hdi_levels(density, masses)))
    fig, ax = plt.subplots(figsize=(4.5, 4))
    contour = ax.contour(x * 100, y * 100, density, levels=levels, cmap="viridis")
    labels = {lev: f"{int(m * 100)}%" for lev, m in zip(hdi_levels(density, masses), masses)}
    ax.clabel(contour, fmt=lambda v: labels.get(v, ""), fontsize=7)
    if truth is not None:
        ax.plot(truth[0] * 100, truth[1] * 100, "r+", ms=12, label="truth")
        ax.legend(fontsize=8)
    ax.set_xlabel("x (cm)")
    ax.set_ylabel("y (cm)")
    ax.set_aspect("equal")
    ax.set_title("translation posterior (HDI 5-80%)", fontsize=10)
    fig.tight_layout()
    return save_figure(fig, path)


def colour_posterior(colour: np.ndarray, path: str | Path, truth: Sequence[float] | None = None) -> Path:
    """Histograms of the colour channels and swatches of posterior draws."""
    plt = _pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(12, 2.8))
    for c, (name, tint) in enumerate(zip("RGB", ("tab:red", "tab:green", "tab:blue"))):
        axes[c].hist(colour[:, c], bins=50, color=tint, alpha=0.8, density=True)
        if truth is not None:
            axes[c].axvline(truth[c], color="k", ls="--")
        axes[c].set_title(f"colour {name}", fontsize=9)
    rng = np.random.default_rng(0)
    swatches = np.clip(colour[rng.choice(len(colour), size=64)], 0, 1).reshape(8, 8, 3)
    axes[3].imshow(swatches, interpolation="nearest")
    axes[3].set_title("64 posterior draws", fontsize=9)
    axes[3].axis("off")
    fig.tight_layout()
    return save_figure(fig, path)


def trace_plot(idata, path: str | Path, variables: Sequence[str] = ("shift", "scale", "colour", "kappa")) -> Path:
    """ArviZ trace plot of the main variables."""
    import arviz as az

    _pyplot()  # the Agg backend, before ArviZ draws
    axes = az.plot_trace(idata, var_names=list(variables), compact=True, figsize=(10, 2.2 * len(variables)))
    fig = np.asarray(axes).ravel()[0].figure
    fig.tight_layout()
    return save_figure(fig, path)


def island_evidence(hypotheses: dict, path: str | Path, steps: Sequence[dict] | None = None) -> Path:
    """An SMC posterior's own diagnostic. Left: each independent run's log evidence per hypothesis
    (dots; beside them, where the run also estimated it by importance sampling, its tempered (x) and
    importance (+) estimates, whose mean it keeps), their pooled estimate (bar) and the posterior weight;
    runs of one hypothesis that disagree by more than a few nats found different poses: the answer then
    depends on the seed. With the
    run's ``steps`` (:func:`mitsuba_p3.infer.tempering.record`), two more panels per step and run:
    the temperature lambda, and the incremental weights' ESS with each move's acceptance."""
    plt = _pyplot()
    names = list(hypotheses)
    panels = 3 if steps else 1
    figure, axes = plt.subplots(1, panels, figsize=(1.2 + 1.1 * len(names) + 3.4 * (panels - 1), 3.2), squeeze=False,
                                gridspec_kw={"width_ratios": [1.2 + 1.1 * len(names)] + [3.4] * (panels - 1)})
    ax = axes[0][0]
    for i, name in enumerate(names):
        runs = hypotheses[name].get("island_log_evidence") or []
        ax.hlines(hypotheses[name]["log_evidence"], i - 0.3, i + 0.3, color="C0", lw=2)
        offsets = np.full(len(runs), i, float) + np.linspace(-0.15, 0.15, len(runs))
        ax.plot(offsets, runs, "o", color="C1", ms=5, label="run (kept)" if i == 0 else None)
        # with the importance-sampling evidence: the two estimates each run's kept one is the mean of
        for key, marker, label in (("island_log_evidence_tempered", "x", "tempered"),
                                   ("island_log_evidence_importance", "+", "importance")):
            if hypotheses[name].get(key):
                ax.plot(offsets + 0.08, hypotheses[name][key], marker, color="0.4", ms=4,
                        label=label if i == 0 else None)
        gap = f"\ngap {max(runs) - min(runs):.1f}" if len(runs) > 1 else ""
        ax.annotate(f"p = {hypotheses[name]['weight']:.2f}{gap}", (i, hypotheses[name]["log_evidence"]),
                    textcoords="offset points", xytext=(0, 8), ha="center", fontsize=7)
    low, high = ax.get_ylim()
    ax.set_ylim(low, high + 0.2 * (high - low))          # room for the labels above the highest
    ax.set_xticks(range(len(names)), names, fontsize=8)
    ax.set_ylabel("log evidence (nats)")
    ax.set_title("runs per hypothesis (bar: pooled; dots: runs)", fontsize=8)
    if any(hypotheses[name].get("island_log_evidence_tempered") for name in names):
        ax.legend(fontsize=6, loc="lower right")
    if steps:
        _tempering_panels(axes[0][1], axes[0][2], names, steps)
    figure.tight_layout()
    return save_figure(figure, path)


def _tempering_panels(lam_ax, ess_ax, names: list, steps: Sequence[dict]) -> None:
    """lambda per step (one line per run, coloured by hypothesis), and the ESS share of each step's
    incremental weights (dots) with the walk acceptance (line) averaged over the runs."""
    runs: dict = {}
    segment = 0           # a new tempering call (a round, or the bridge) starts where the rows change or lambda falls
    for number, record in enumerate(steps):
        previous = steps[number - 1] if number else record
        if record["rows"] != previous["rows"] or any(a < b for a, b in zip(record["tempering"], previous["tempering"])):
            segment += 1
        for column, (row, lam) in enumerate(zip(record["rows"], record["tempering"])):
            runs.setdefault((segment, column, row), []).append((number + 1, lam))
    for (_, _, row), points in runs.items():
        x, y = zip(*points)
        lam_ax.plot(x, y, color=f"C{row}", lw=1, alpha=0.8, marker=".", ms=3)
    for row, name in enumerate(names):
        lam_ax.plot([], [], color=f"C{row}", label=name)
    lam_ax.set_yscale("log")
    lam_ax.set_xlabel("step")
    lam_ax.set_ylabel("temperature lambda")
    lam_ax.legend(fontsize=6)
    lam_ax.set_title("tempering path per run", fontsize=8)
    x = np.arange(1, len(steps) + 1)
    ess_ax.plot(x, [np.mean(r["ess"]) for r in steps], "o", color="C0", ms=3, label="ESS share of the weights")
    ess_ax.plot(x, [np.mean(r.get("walk_acceptance", np.nan)) for r in steps], color="C1", lw=1,
                label="walk acceptance")
    ess_ax.plot(x, [np.mean(r.get("material_acceptance", np.nan)) for r in steps], color="C2", lw=1,
                label="material acceptance")
    for colour, move in (("C3", "gradient"), ("C4", "turn")):
        if any(f"{move}_acceptance" in r for r in steps):
            ess_ax.plot(x, [np.mean(r.get(f"{move}_acceptance", np.nan)) for r in steps], color=colour, lw=1,
                        label=f"{move} acceptance")
    ess_ax.set_ylim(0, 1.05)
    ess_ax.set_xlabel("step")
    ess_ax.legend(fontsize=6, loc="center left", framealpha=0.6)
    ess_ax.set_title("ESS and acceptance (mean over runs)", fontsize=8)


def wilson_interval(accuracy: np.ndarray, count: np.ndarray, z: float = 1.96) -> tuple[np.ndarray, np.ndarray]:
    """The Wilson score interval (95% at z = 1.96) of a share ``accuracy`` of ``count`` trials: honest for the
    few-query bins of a reliability diagram, where the normal interval leaves [0, 1]."""
    accuracy, count = np.asarray(accuracy, np.float64), np.asarray(count, np.float64)
    centre = (accuracy + z * z / (2 * count)) / (1 + z * z / count)
    half = z * np.sqrt(accuracy * (1 - accuracy) / count + z * z / (4 * count * count)) / (1 + z * z / count)
    return centre - half, centre + half


def reliability_diagram(path: str | Path, results: dict, settings: Sequence[str]) -> Path:
    """Accuracy against confidence per few-shot setting, one line per model (``results``: model ->
    its evaluation results, whose accuracy per setting carries the reliability bins; a lower-case
    model name such as ``p3`` is shown in capitals). Each bin's marker grows with its queries and
    carries its accuracy's 95% Wilson interval, so a bin of three queries reads as the guess it is."""
    plt = _pyplot()
    settings = [name for name in settings if any(name in r["accuracy"] for r in results.values())]
    figure, axes = plt.subplots(1, len(settings), figsize=(3.2 * len(settings), 3.2), squeeze=False)
    for ax, name in zip(axes[0], settings):
        ax.plot([0, 1], [0, 1], color="0.6", lw=1, ls="--")
        for i, (likelihood, result) in enumerate(results.items()):
            acc = result["accuracy"].get(name)
            if not acc:
                continue
            bins = [b for b in acc["reliability"] if b[2] > 0]
            if not bins:
                continue
            confidence, accuracy, count = np.array(bins, np.float64).T
            low, high = wilson_interval(accuracy, count)
            colour = plt.cm.tab10(i % 10)
            ax.plot(confidence, accuracy, color=colour, lw=0.8, alpha=0.5)
            error = np.clip([accuracy - low, high - accuracy], 0.0, None)    # (a rounding below zero at 0 or 1)
            ax.errorbar(confidence, accuracy, yerr=error, fmt="none", ecolor=colour, elinewidth=0.8, capsize=2)
            ax.scatter(confidence, accuracy, s=8 + 60 * np.sqrt(count / count.max()), color=colour, zorder=3,
                       label=f"{likelihood.upper() if likelihood.islower() else likelihood} (ECE {acc['ece']:.3f})")
        ax.set_title(name)
        ax.set_xlabel("confidence")
        ax.set_xlim(0, 1)
        ax.set_ylim(0, 1)
        ax.legend(fontsize=7, loc="upper left")
    axes[0][0].set_ylabel("accuracy")
    return save_figure(figure, path)


def _bar_panels(panels: dict[str, dict[str, dict]], categories: Sequence[str], ticks: Sequence[str],
                height: float):
    """Grouped bars, one panel per key of ``panels`` (-> {row name: {category: (value, error)}}), one
    group per category, one colour per row name across panels; values in [0, 1], drawn in %."""
    plt = _pyplot()
    names = list(dict.fromkeys(row for rows in panels.values() for row in rows))
    colours = {name: plt.cm.tab10(i % 10) for i, name in enumerate(names)}
    figure, axes = plt.subplots(1, len(panels), figsize=(4.2 * len(panels), height), squeeze=False, sharey=True)
    x = np.arange(len(categories))
    for ax, (title, rows) in zip(axes[0], panels.items()):
        width = 0.8 / max(len(rows), 1)
        for i, (name, cells) in enumerate(rows.items()):
            values, errors = np.array([cells.get(c, (np.nan, 0.0)) for c in categories], np.float64).T
            ax.bar(x - 0.4 + (i + 0.5) * width, 100 * values, width, yerr=100 * errors if errors.any() else None,
                   capsize=2, color=colours[name], label=name)
        ax.set_title(title)
        ax.set_xticks(x, ticks)
        ax.set_ylim(0, 100)
        ax.grid(axis="y", alpha=0.3)
    return figure, axes[0]


def accuracy_bars(path: str | Path, panels: dict[str, dict[str, dict]], settings: Sequence[str],
                  reference: dict[str, Sequence[float]] | None = None) -> Path:
    """Few-shot accuracy per setting as grouped bars, one panel per benchmark. ``panels``: benchmark ->
    {row name: {setting: (mean, 95% half-width)}}; ``reference``: benchmark -> one accuracy (%) per
    setting (the paper's P3, drawn as black ticks)."""
    figure, axes = _bar_panels(panels, settings, [s.replace("-way ", "w").replace("-shot", "s") for s in settings],
                               3.6)
    for ax, benchmark in zip(axes, panels):
        if reference and benchmark in reference:
            ax.scatter(np.arange(len(settings)), reference[benchmark], marker="_", s=400, color="black", zorder=3,
                       label="paper P3")
    axes[0].set_ylabel("accuracy (%), 95% interval")
    handles = {h.get_label(): h for ax in axes for h in ax.get_legend_handles_labels()[0]}
    lines = -(-len(handles) // 4)
    figure.tight_layout(rect=(0, 0.06 * lines, 1, 1))
    figure.legend(handles.values(), handles.keys(), loc="lower center", ncol=min(len(handles), 4), fontsize=8)
    return save_figure(figure, path)


def attribute_bars(path: str | Path, panels: dict[str, dict[str, dict]]) -> Path:
    """Attribute recovery (share of test images whose posterior names the attribute right) as bars,
    one panel per benchmark; ``panels``: benchmark -> {row name: {attribute: accuracy}}."""
    attributes = list(dict.fromkeys(a for rows in panels.values() for cells in rows.values() for a in cells))
    figure, axes = _bar_panels({b: {row: {a: (v, 0.0) for a, v in cells.items()} for row, cells in rows.items()}
                                for b, rows in panels.items()}, attributes, attributes, 3.4)
    for ax in axes:
        ax.tick_params(axis="x", labelrotation=30)
        ax.legend(fontsize=7, loc="lower left")
    axes[0].set_ylabel("right (%) of test images")
    figure.tight_layout()
    return save_figure(figure, path)


def sbc_figures(summary: dict, result, path: Path) -> None:
    """The SBC figure: per coordinate the ECDF difference with its simultaneous 95% band (top two
    rows) and the rank histogram with a uniform histogram's 99% band (bottom two), and the shape
    posterior's reliability diagram (a separate ``calibration.png`` beside ``path``)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from scipy.stats import binom

    from .evaluate.sbc import CHECKED, ecdf_bands, ecdf_difference

    n, bins = summary["images"], summary["bins"]
    z, lower, upper = ecdf_bands(n)
    difference = ecdf_difference(result.ranks, result.draws, z)
    fig, axes = plt.subplots(4, 4, figsize=(13, 9))
    for j, (ax, name) in enumerate(zip(axes[:2].ravel(), CHECKED)):
        ax.fill_between(z, lower, upper, color="0.85", lw=0)
        inside = summary["ecdf_inside_95_band"][name]
        ax.plot(z, difference[:, j], color="tab:blue" if inside else "tab:red", lw=1.2)
        ax.axhline(0, color="0.5", lw=0.6)
        ax.set_title(f"{name}  KS p={summary['rank_uniformity_ks_p'][name]:.2g}", fontsize=9)
        ax.tick_params(labelsize=7)
    low, high = binom.ppf([0.005, 0.995], n, 1 / bins)
    for ax, name in zip(axes[2:].ravel(), CHECKED):
        ax.axhspan(low, high, color="0.85")
        ax.bar(np.arange(bins), summary["rank_counts"][name], color="tab:blue")
        ax.set_title(f"{name}  chi2 p={summary['rank_uniformity_p'][name]:.2g}", fontsize=9)
        ax.set_xticks([])
        ax.tick_params(labelsize=7)
    axes[0][0].set_ylabel("ECDF - uniform")
    axes[2][0].set_ylabel("rank count")
    fig.suptitle(f"SBC: {n} simulations, {summary['draws']} draws each. Top: ECDF difference, grey the "
                 "simultaneous 95% band (red: leaves it). Bottom: rank histograms, grey a uniform's 99% band",
                 fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    bins_ = [b for b in summary["class"]["reliability"] if b[2] > 0]
    fig, ax = plt.subplots(figsize=(3.6, 3.4))
    ax.plot([0, 1], [0, 1], ls="--", color="0.6", lw=1)
    ax.plot([b[0] for b in bins_], [b[1] for b in bins_], "o-", color="tab:blue")
    for b in bins_:
        ax.annotate(str(b[2]), (b[0], b[1]), textcoords="offset points", xytext=(4, -10), fontsize=7)
    ax.set_xlabel("confidence of the modal shape")
    ax.set_ylabel("share correct")
    ax.set_title(f"shape calibration: ECE {summary['class']['ece']:.3f}", fontsize=9)
    fig.tight_layout()
    fig.savefig(path.with_name("calibration.png"), dpi=110)
    plt.close(fig)
