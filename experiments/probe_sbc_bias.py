"""What does an SBC run's rank bias follow? Ranks against the simulations' true values, and per class.

An SBC cache (``mitsuba-p3 sbc ... --out DIR``'s ``DIR/cache.npz``) keeps each simulation's ranks, shape
probabilities and true class, not its true coordinates. Every simulation is seeded by (seed, i)
(:func:`mitsuba_p3.evaluate.sbc.run_sbc`), so its scene is drawn again here from the same stream, without
a sampler; the true class must match the cache's, a check that the model and seed are the run's. For each
checked coordinate it prints the mean rank (uniform: L / 2), the Spearman correlation of its rank with
every true coordinate and the yaw (modulo a quarter turn), and per shape class the mean rank, the rank
KS p-value and the share of simulations whose truth lies outside all draws. With ``--masks``, per class
also how many scenes' object pixels differ between the JAX tracer's silhouette (on which SBC draws the
shading fields) and Mitsuba's render (whose pixels inference takes), and the first coordinate's mean rank
with and without a difference.

    python experiments/probe_sbc_bias.py results/sbc-rounds2 --model data/models/fsclvr-fields3 --noise fields

With ``--rerun CLASS``, the simulations of that class are sampled again, each exactly as the SBC run did
(:func:`mitsuba_p3.evaluate.sbc.run_sbc`'s seeds, the same scene, fields and draws), under the sampler
settings ``--set`` changes (e.g. ``smc.footprint=false``), and their ranks printed beside the run's. The
reruns are cached in ``--out`` (resumable); ``--part K/M`` samples every M-th of them, starting at the K-th,
so M processes can share the cores, and a run without ``--part`` reads every part's cache:

    python experiments/probe_sbc_bias.py results/sbc-rounds2 --model data/models/fsclvr-fields3 --noise fields \
        --rerun sphere --set smc.footprint=false --out out/sbc-spheres-nofootprint --part 0/2
"""
from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np


def class_table(ranks: np.ndarray, classes: np.ndarray, draws: int) -> list[dict]:
    """Per class of ``classes`` (n,): its count, and per column of ``ranks`` (n, d) the mean rank, the
    KS p-value of the ranks' uniformity and the share of ranks at 0 or ``draws``."""
    from mitsuba_p3.evaluate.sbc import ks_uniformity

    rows = []
    for cls in np.unique(classes):
        mine = ranks[classes == cls]
        rows.append({"class": int(cls), "count": int(len(mine)), "mean_rank": mine.mean(axis=0),
                     "ks_p": ks_uniformity(mine, draws), "outside": ((mine == 0) | (mine == draws)).mean(axis=0)})
    return rows


def rerun(core, config, simulations: list[int], seed: int, draws: int, cache: Path) -> dict[int, np.ndarray]:
    """Ranks (8,) of each of ``simulations`` (indices of an SBC run with ``seed`` and ``draws``) sampled
    again under ``config``, each simulated and ranked with the run's own random stream; cached in
    ``cache`` (an .npz of indices and ranks) after every simulation, so a killed rerun resumes."""
    from mitsuba_p3.evaluate.sbc import simulate_and_rank, smc_sampler
    from mitsuba_p3.files import atomic_npz

    done: dict[int, np.ndarray] = {}
    if cache.exists():
        with np.load(cache) as f:
            done = dict(zip(f["indices"].tolist(), f["ranks"]))
    sample = smc_sampler(core, config)
    for i in simulations:
        if i in done:
            continue
        done[i] = simulate_and_rank(core, sample, seed, i, draws, config.window)[0]
        atomic_npz(cache, indices=np.array(list(done)), ranks=np.array(list(done.values())))
        print(f"simulation {i}: ranks {done[i].tolist()} ({len(done)} done)", flush=True)
    return done


def main() -> None:
    import jax.numpy as jnp
    from scipy.stats import spearmanr

    from mitsuba_p3.evaluate.sbc import CHECKED, _simulate, checked_values, ks_uniformity, model_core
    from mitsuba_p3.shapes import SHAPES
    from mitsuba_p3.space import render_params

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("folder", type=Path, help="an SBC output folder with cache.npz")
    parser.add_argument("--model", required=True, help="the fitted model the run simulated from")
    parser.add_argument("--noise", default="fitted")
    parser.add_argument("--coordinates", default="shift_x,shift_y")
    parser.add_argument("--masks", action="store_true", help="compare the tracer's and the render's object pixels")
    parser.add_argument("--rerun", choices=SHAPES, help="sample this class's simulations again (--set)")
    parser.add_argument("--set", action="append", default=[], help="a sampler setting for --rerun: smc.FIELD=VALUE")
    parser.add_argument("--out", type=Path, help="--rerun's cache folder")
    parser.add_argument("--part", default="0/1", help="--rerun: K/M, every M-th simulation from the K-th")
    args = parser.parse_args()
    with np.load(args.folder / "cache.npz") as cache:
        ranks, classes = cache["ranks"], cache["truths"]
        draws, seed = int(cache["draws"]), int(cache["seed"])
    core = model_core(args.model, "mitsuba", (120, 160), args.noise)
    truths, differ = [], []
    for i in range(len(ranks)):
        image, x, cls, z, *_ = _simulate(core, np.random.default_rng([seed, i]))
        if cls != classes[i]:
            raise SystemExit(f"simulation {i}: class {cls} drawn, the cache has {classes[i]}: another model or seed")
        truths.append(np.concatenate([checked_values(x), [float(x["theta"]) % (np.pi / 2)]]))
        if args.masks:
            traced = np.asarray(core.objects(jnp.asarray(z), core.observe(image))).reshape(image.shape[:2])
            _, rendered = core.renderer.render({k: np.asarray(v) for k, v in render_params(x).items()}, objects=True)
            differ.append(int((traced != rendered).sum()))
    truths = np.array(truths)
    names = list(CHECKED) + ["yaw mod 90"]
    table = class_table(ranks, classes, draws)
    for name in args.coordinates.split(","):
        j = CHECKED.index(name)
        print(f"{name}: mean rank {ranks[:, j].mean():.1f} (uniform {draws / 2:.1f}), {len(ranks)} simulations")
        for k, other in enumerate(names):
            rho, p = spearmanr(truths[:, k], ranks[:, j])
            print(f"    rank vs true {other}: Spearman {rho:+.3f} (p {p:.3g})")
        for row in table:
            print(f"    {SHAPES[row['class']]} ({row['count']}): mean rank {row['mean_rank'][j]:.1f}, KS p "
                  f"{row['ks_p'][j]:.3g}, truth outside all draws {row['outside'][j]:.1%}")
    if args.rerun:
        from mitsuba_p3.cli.settings import apply_settings
        from mitsuba_p3.infer.smc import SMCConfig

        if args.out is None:
            raise SystemExit("--rerun needs --out")
        args.out.mkdir(parents=True, exist_ok=True)
        part, parts = (int(v) for v in args.part.split("/"))
        mine = [int(i) for i in np.flatnonzero(classes == SHAPES.index(args.rerun))]
        config = apply_settings(SMCConfig(), args.set)
        if parts > 1:
            rerun(core, config, mine[part::parts], seed, draws, args.out / f"part{part}of{parts}.npz")
            return
        again: dict = {}
        for cache in sorted(args.out.glob("part*.npz")) + sorted(args.out.glob("all.npz")):
            with np.load(cache) as f:
                again.update(zip(f["indices"].tolist(), f["ranks"]))
        missing = [i for i in mine if i not in again]
        if missing:
            again.update(rerun(core, config, missing, seed, draws, args.out / "all.npz"))
        both = np.array(mine)
        before, after = ranks[both], np.array([again[i] for i in mine])
        print(f"{args.rerun}, {len(mine)} simulations, under {' '.join(args.set) or 'the default'} against the run:")
        for j, name in enumerate(CHECKED):
            print(f"    {name}: mean rank {after[:, j].mean():.1f} (run {before[:, j].mean():.1f}; uniform "
                  f"{draws / 2:.1f}), KS p {ks_uniformity(after, draws)[j]:.3g} (run {ks_uniformity(before, draws)[j]:.3g})")
    if args.masks:
        j, differ = CHECKED.index(args.coordinates.split(",")[0]), np.array(differ)
        for cls in np.unique(classes):
            mine = classes == cls
            some, none = mine & (differ > 0), mine & (differ == 0)
            print(f"{SHAPES[cls]}: object pixels differ in {some.sum()} of {mine.sum()} scenes ({differ[mine].sum()} "
                  f"pixels); mean {CHECKED[j]} rank {ranks[some, j].mean() if some.any() else float('nan'):.1f} "
                  f"with, {ranks[none, j].mean() if none.any() else float('nan'):.1f} without")


if __name__ == "__main__":
    main()
