"""Did a run reach the truth's peak? Per SBC simulation, the best particle of the true shape against the truth.

For SBC's simulations (:func:`~mitsuba_p3.evaluate.sbc.simulate`, seeded by (seed, i) and sampled with the
seed ``mitsuba-p3 sbc`` gives them), this runs the SMC under each setting and reports, per simulation:

- the **deficit**: the log likelihood of the true scene minus that of the best final particle of the true
  shape's runs. A run that reached the truth's peak has a negative deficit (its best particle fits the noise a
  little better than the truth does: about half the number of constrained coordinates); a run stuck in a
  local optimum of the pose has a positive one, often tens of nats;
- the **other shapes' excess**: the best final particle of the other shapes' runs minus the truth's log
  likelihood (near 0 or above: another shape explains the image as well, a close call; hundreds of nats
  below with a deficit as large: every run lost the object);
- the **island gap** of the true shape (its two runs' log evidence apart), every run's log evidence, and
  the shape the run chose;
- the walk's final acceptance and the run's seconds.

    python experiments/probe_sbc_modes.py --model data/models/fsclvr-lo --simulations 4 5 10 16 30 \\
        --configs '{"chart": {}, "plain": {"chart": false}}'
    python experiments/probe_sbc_modes.py --model data/models/fsclvr-lo --simulations 28 46 78 116 118 166 173 182 \
        --configs '{"inside": {}, "window_alone": {"inside_window": false}}'
"""
import argparse
import json

import numpy as np


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--simulations", type=int, nargs="+", required=True, help="simulation indices i")
    parser.add_argument("--seed", type=int, default=0, help="the SBC run's seed")
    parser.add_argument("--configs", default='{"default": {}}', help="JSON: name -> SMCConfig fields")
    args = parser.parse_args()

    import jax
    import jax.numpy as jnp

    from mitsuba_p3.evaluate.sbc import model_core, simulate
    from mitsuba_p3.infer.smc import SMCConfig, sample_smc
    from mitsuba_p3.shapes import SHAPES

    core = model_core(args.model)
    loglik = jax.jit(jax.vmap(core.log_likelihood, in_axes=(0, None)))
    report = {}
    for name, fields in json.loads(args.configs).items():
        rows = []
        for i in args.simulations:
            rng = np.random.default_rng([args.seed, i])
            truth = core.prior.sample(np.random.default_rng([args.seed, i]), 1)[0].astype(np.float32)
            image, _, cls = simulate(core, rng)          # the same draws as simulate's own prior sample
            run = sample_smc(core, core.observe(image), SMCConfig(**fields, seed=int(rng.integers(2 ** 31))))
            window = run.statistics["window"]
            observation = core.observe(image, tuple(window)) if window else core.observe(image)
            particles = run.particles.rows
            mine = np.nonzero(particles.index == cls)[0]
            best = max(float(particles.state[1][r].max()) for r in mine)
            others = np.nonzero(particles.index != cls)[0]
            best_other = max(float(particles.state[1][r].max()) for r in others)
            weights = {h: v["weight"] for h, v in run.statistics["hypotheses"].items()}
            row = {"simulation": i, "shape": SHAPES[cls],
                   "deficit": float(loglik(jnp.asarray(truth[None]), observation)[0]) - best,
                   "other_excess": best_other - float(loglik(jnp.asarray(truth[None]), observation)[0]),
                   "log_evidence": {h: [round(float(e), 1) for e in v["island_log_evidence"]]
                                    for h, v in run.statistics["hypotheses"].items()},
                   "island_gap": float(np.ptp(particles.log_evidence[mine])) if len(mine) > 1 else None,
                   "chosen": max(weights, key=weights.get).split("/")[0],
                   "walk_acceptance": run.statistics["walk_acceptance"], "seconds": run.statistics["seconds"]}
            rows.append(row)
            print(f"{name} simulation {i} ({row['shape']}): deficit {row['deficit']:.1f}, other shapes' best "
                  f"{row['other_excess']:+.1f} over the truth, island gap "
                  f"{row['island_gap'] if row['island_gap'] is None else round(row['island_gap'], 1)}, chose "
                  f"{row['chosen']}, walk acceptance {row['walk_acceptance']:.2f}, {row['seconds']:.1f} s", flush=True)
        report[name] = {"config": fields, "simulations": rows,
                        "deficit_median": float(np.median([r["deficit"] for r in rows])),
                        "stuck": int(sum(r["deficit"] > 10 for r in rows)),
                        "shape_right": float(np.mean([r["chosen"] == r["shape"] for r in rows]))}
    print(json.dumps(report, indent=2))


if __name__ == "__main__":
    main()
