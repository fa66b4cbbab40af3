"""Do the scoring window or the footprint start explain where SBC fails? Both, per simulation.

The SMC scores a window around the image's footprint (:meth:`~mitsuba_p3.infer.model.PosteriorCore.window_for`).
For SBC's simulations (:func:`~mitsuba_p3.evaluate.sbc.simulate`, seeded by (seed, i) as ``mitsuba-p3 sbc``
seeds them), this renders each simulated scene without noise, marks the pixels where it differs from the
empty floor by more than 0.02 (object and shadow), and reports the share of them inside the window the
sampler would choose from the noisy image; beside it, the simulation's ranks from an SBC cache
(position and height ranks at 0 or at the number of draws: the truth outside every draw); and where the
footprint proposal (:class:`~mitsuba_p3.infer.footprint.FootprintProposal`, the SMC's first draws) centres
its mixture, against the truth's position; and whether the true object's centre appears inside the window
(the scenes the SMC may reach: a centre outside it has likelihood zero, :mod:`mitsuba_p3.infer.window`).

    python experiments/probe_sbc_windows.py --model data/models/fsclvr-lo --cache results/sbc-moves/default/cache.npz
    python experiments/probe_sbc_windows.py --model data/models/fsclvr-lo --cache results/sbc-moves/inside/cache.npz \
        --start 88
"""
import argparse

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--cache", required=True, help="an SBC run's cache.npz (same model and seed)")
    parser.add_argument("--resolution", default="120x160")
    parser.add_argument("--start", type=int, default=0, help="the first simulation to look at")
    args = parser.parse_args()
    from mitsuba_p3.evaluate.sbc import model_core, simulate
    from mitsuba_p3.fit.noise import SCORING_WINDOW
    from mitsuba_p3.infer.footprint import FootprintProposal, footprint_mask
    from mitsuba_p3.space import render_params

    core = model_core(args.model, "mitsuba", tuple(int(v) for v in args.resolution.split("x")))
    with np.load(args.cache) as cache:
        ranks, draws, seed = cache["ranks"], int(cache["draws"]), int(cache["seed"])
    rows, offsets, centre_outside = [], [], []
    origin, directions = core.camera_rays
    for i in range(args.start, len(ranks)):
        rng = np.random.default_rng([seed, i])
        image, x, _ = simulate(core, rng)
        clean = core.renderer.render({k: np.asarray(v) for k, v in render_params(x).items()})
        changed = np.any(np.abs(clean - core.empty) > 0.02, axis=-1)
        window = core.window_for(image, SCORING_WINDOW)
        if window is None:
            inside = 1.0
        else:
            top, left, h, w = window
            inside = changed[top:top + h, left:left + w].sum() / max(changed.sum(), 1)
            row, col = np.asarray(core.pixel_of(np.array([*x["shift"], x["scale"][2]], np.float32)))
            if not (top - 0.5 <= row < top + h - 0.5 and left - 0.5 <= col < left + w - 0.5):
                centre_outside.append(i)
        outside = bool(np.any(np.isin(ranks[i][[0, 1, 4]], (0, draws))))
        proposal = FootprintProposal.of(footprint_mask(image, core.empty, core.footprint_threshold), origin,
                                        directions, core.prior.config.shift_bound, np.random.default_rng(1))
        if proposal is not None:
            centres = proposal.centres(np.asarray(x["scale"])[None, 2])[0]
            offsets.append(1000 * (centres.mean(axis=0) - np.asarray(x["shift"])))
        rows.append((inside, outside))
        print(f"simulation {i:3d}: changed pixels {changed.sum():5d}, inside the window {inside:.2f}, "
              f"ranks shift_x/shift_y/height {ranks[i][0]:2d}/{ranks[i][1]:2d}/{ranks[i][4]:2d}"
              f"{'  truth outside all draws' if outside else ''}")
    inside, outside = np.array(rows).T
    cut = inside < 0.99
    print(f"\n{len(rows)} simulations: the window cuts object or shadow in {cut.sum()} ({cut.mean():.0%}); "
          f"truth outside all draws (position or height) in {outside[cut].mean():.0%} of those and "
          f"{outside[~cut].mean():.0%} of the others")
    print(f"the true centre outside the window in {len(centre_outside)} ({centre_outside})")
    offsets = np.array(offsets)
    high, low = (ranks[args.start:, 0] == draws).mean(), (ranks[args.start:, 0] == 0).mean()
    print(f"footprint proposal's mean position - truth over {len(offsets)} simulations (mm): mean "
          f"{offsets.mean(axis=0).round(1)}, median {np.median(offsets, axis=0).round(1)}, sd "
          f"{offsets.std(axis=0).round(1)} (x, y); truth above / below all draws of shift_x {high:.0%} / {low:.0%}")


if __name__ == "__main__":
    main()
