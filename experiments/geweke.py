"""Do the SMC's moves leave the posterior invariant? Geweke's successive-conditional check on a fitted model.

SBC of the default sampler fails (``results/sbc-fsclvr``); this separates a wrong move from a search
that misses the posterior's mass (:mod:`mitsuba_p3.evaluate.geweke`). For each shape hypothesis,
``--chains`` chains alternate an image simulated from their state (the JAX tracer at
``--resolution``, the fitted noise at the SBC's effective sigma) and one sweep of the SMC's
moves at lambda = 1, ``--steps`` times; their final states are compared with fresh prior draws.
Prints one JSON line per hypothesis and move set.

    python experiments/geweke.py --model data/models/fsclvr-lo --resolution 60x80 --chains 400 --steps 20
        [--noise fields] [--shapes cube] [--moves material]

With ``--noise fields`` the images are simulated from the shading fields' form (the fields drawn on each
chain's own object, shadow and floor, tinted by its colour where the model's fields are) and the moves
score that form.
"""
import argparse
import json
import time


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--resolution", default="60x80")
    parser.add_argument("--chains", type=int, default=400)
    parser.add_argument("--steps", type=int, default=20)
    parser.add_argument("--moves", default="walk,material,both")
    parser.add_argument("--walk-scale", type=float, default=0.05)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--noise", default="fitted", choices=("fitted", "fields"),
                        help="the likelihood simulated and sampled: the fitted Gaussian, or the shading fields' form")
    parser.add_argument("--shapes", help="only these shape hypotheses (comma-separated names)")
    args = parser.parse_args()
    from mitsuba_p3.evaluate.geweke import geweke_check
    from mitsuba_p3.evaluate.sbc import model_core
    from mitsuba_p3.shapes import SHAPES

    core = model_core(args.model, "jax", tuple(int(v) for v in args.resolution.split("x")), args.noise)
    for hypothesis, shape in enumerate(SHAPES):
        if args.shapes and shape not in args.shapes.split(","):
            continue
        begin = time.perf_counter()
        result = geweke_check(core, hypothesis, tuple(args.moves.split(",")), args.chains, args.steps, args.seed,
                              args.walk_scale)
        print(json.dumps({"model": args.model, "resolution": args.resolution, "noise": args.noise,
                          "channels": core.config.fields_channels if args.noise == "fields" else None,
                          "sigma": core.config.sigma,
                          "hypothesis": shape, "seconds": round(time.perf_counter() - begin, 1),
                          **result.summary()}), flush=True)


if __name__ == "__main__":
    main()
