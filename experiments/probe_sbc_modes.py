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
- the walk's final acceptance and the run's seconds;
- the same deficit in the log **target** (log prior + log likelihood), and where the truth's height
  (log_scale_z) and y position fall among the true shape's final particles (their share below the truth:
  near 1 for the height, 0 for y, was the lean of results/sbc-importance, whose sampler scored another window
  than its fields': results/sbc-window).

With ``--noise fields`` each simulation is the shading fields' one, drawn exactly as ``mitsuba-p3 sbc --noise
fields`` draws it (:func:`~mitsuba_p3.evaluate.sbc.simulate_scored` on the config's window, the same seeds), so
its numbers belong to that run's cache.

    python experiments/probe_sbc_modes.py --model data/models/fsclvr-lo --simulations 4 5 10 16 30 \\
        --configs '{"chart": {}, "plain": {"chart": false}}'
    python experiments/probe_sbc_modes.py --model data/models/fsclvr-lo --simulations 28 46 78 116 118 166 173 182 \
        --configs '{"inside": {}, "window_alone": {"inside_window": false}}'
    python experiments/probe_sbc_modes.py --model data/models/fsclvr-tinted --noise fields --simulations 3 7 11
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
    parser.add_argument("--noise", default="fitted", choices=("fitted", "sandwich", "fields"),
                        help="the SBC run's noise form (mitsuba-p3 sbc --noise)")
    args = parser.parse_args()

    from dataclasses import replace

    import jax
    import jax.numpy as jnp

    from mitsuba_p3.evaluate.sbc import model_core, simulate_scored
    from mitsuba_p3.infer.smc import SMCConfig, sample_smc
    from mitsuba_p3.shapes import SHAPES
    from mitsuba_p3.space import SLICES

    core = model_core(args.model, noise=args.noise)
    loglik = jax.jit(jax.vmap(core.log_likelihood, in_axes=(0, None)))
    logprior = jax.jit(jax.vmap(core.prior.log_prob))
    height, y = SLICES["scale"].start + 2, SLICES["shift"].start + 1
    report = {}
    for name, fields in json.loads(args.configs).items():
        rows = []
        for i in args.simulations:
            rng = np.random.default_rng([args.seed, i])
            truth = core.prior.sample(np.random.default_rng([args.seed, i]), 1)[0].astype(np.float32)
            config = SMCConfig(**fields)
            # the same draws as the SBC run's (simulate_and_rank): the scene, the fields on its window, the seed
            image, _, cls, where = simulate_scored(core, rng, config.window)
            run = sample_smc(core, core.observe(image), replace(config, seed=int(rng.integers(2 ** 31))), window=where)
            window = run.statistics["window"]
            observation = core.observe(image, tuple(window)) if window else core.observe(image)
            particles = run.particles.rows
            mine = np.nonzero(particles.index == cls)[0]
            state = particles.state
            best = max(float(state.loglikelihood[r].max()) for r in mine)
            best_target = max(float((state.loglikelihood[r] + state.logprior[r]).max()) for r in mine)
            others = np.nonzero(particles.index != cls)[0]
            best_other = max(float(state.loglikelihood[r].max()) for r in others)
            weights = {h: v["weight"] for h, v in run.statistics["hypotheses"].items()}
            true_loglik = float(loglik(jnp.asarray(truth[None]), observation)[0])
            true_target = true_loglik + float(logprior(jnp.asarray(truth[None]))[0])
            positions = np.concatenate([state.position[r] for r in mine])
            row = {"simulation": i, "shape": SHAPES[cls],
                   "deficit": true_loglik - best, "target_deficit": true_target - best_target,
                   "height_below_truth": float(np.mean(positions[:, height] < truth[height])),
                   "y_below_truth": float(np.mean(positions[:, y] < truth[y])),
                   "other_excess": best_other - true_loglik,
                   "log_evidence": {h: [round(float(e), 1) for e in v["island_log_evidence"]]
                                    for h, v in run.statistics["hypotheses"].items()},
                   "island_gap": float(np.ptp(particles.log_evidence[mine])) if len(mine) > 1 else None,
                   "chosen": max(weights, key=weights.get).split("/")[0],
                   "walk_acceptance": run.statistics["walk_acceptance"], "seconds": run.statistics["seconds"]}
            rows.append(row)
            print(f"{name} simulation {i} ({row['shape']}): deficit {row['deficit']:.1f} (target "
                  f"{row['target_deficit']:.1f}), particles below the truth: height {row['height_below_truth']:.2f}, "
                  f"y {row['y_below_truth']:.2f}; other shapes' best "
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
