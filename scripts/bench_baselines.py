"""Benchmark the baselines' hot loops, the Conv-4's max-pool written two ways; prints one JSON document.

Times, side by side in one run on the same random tasks (median of ``--repeats``, seconds):

- one meta-training iteration (``meta_batch`` tasks, forward and backward, Adam) of
  ProtoNets and first-order MAML, at 56 and 84 px, 5-way and 10-way 1-shot;
- one MAML test episode (10 inner steps on the support, then the queries), 5-way 1-shot;

once with the pooling the backbone uses (:func:`mitsuba_p3.baselines.conv4.max_pool2`, a
reshape and a max) and once with ``lax.reduce_window`` (its gradient is XLA's
``select_and_scatter``), with their ratio and the difference of their losses.

    python scripts/bench_baselines.py [--repeats 3] [--resolutions 56,84]
"""
from __future__ import annotations

import argparse
import json
import statistics
import sys
import time

import numpy as np

QUERIES = 5     # query shots per class in a training task (a benchmark's 6 shots less the support)


def reduce_window_pool(x):
    import jax
    import jax.numpy as jnp

    return jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")


def _median(fn, repeats: int) -> float:
    fn()    # compile
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def _tasks(rng, resolution: int, way: int, count: int):
    return tuple((rng.random((way, resolution, resolution, 3), np.float32), np.arange(way),
                  rng.random((way * QUERIES, resolution, resolution, 3), np.float32),
                  np.repeat(np.arange(way), QUERIES)) for _ in range(count))


def measure(method: str, resolution: int, way: int, repeats: int, meta_batch: int = 2) -> dict:
    """Seconds per meta-iteration (and per MAML test episode) with each pooling, and the loss difference."""
    import jax
    import optax

    from mitsuba_p3.baselines import conv4
    from mitsuba_p3.baselines.methods import METHODS

    model = METHODS[method]()
    params = model.init(jax.random.PRNGKey(0), resolution)
    optimiser = optax.adam(1e-3)
    opt_state = optimiser.init(params)
    tasks = _tasks(np.random.default_rng(0), resolution, way, meta_batch)
    support, labels, queries, _ = tasks[0]

    def build():
        @jax.jit
        def update(params, opt_state, tasks):
            def loss(p):
                return sum(model.task_loss(p, (*task, way))[0] for task in tasks) / len(tasks)

            value, grads = jax.value_and_grad(loss)(params)
            updates, opt_state = optimiser.update(grads, opt_state, params)
            return optax.apply_updates(params, updates), opt_state, value

        return update, jax.jit(model.predict, static_argnums=4)

    out, losses = {}, {}
    used = conv4.max_pool2
    try:
        for name, pool in (("reshape", used), ("reduce_window", reduce_window_pool)):
            conv4.max_pool2 = pool
            update, predict = build()
            losses[name] = float(update(params, opt_state, tasks)[2])
            out[f"iteration_s_{name}"] = _median(lambda: jax.block_until_ready(update(params, opt_state, tasks)), repeats)
            if method == "maml":
                out[f"test_episode_s_{name}"] = _median(
                    lambda: jax.block_until_ready(predict(params, support, labels, queries, way)), repeats)
    finally:
        conv4.max_pool2 = used
    out["iteration_speedup"] = out["iteration_s_reduce_window"] / out["iteration_s_reshape"]
    if method == "maml":
        out["test_episode_speedup"] = out["test_episode_s_reduce_window"] / out["test_episode_s_reshape"]
    out["loss_difference"] = abs(losses["reshape"] - losses["reduce_window"])
    return {k: round(v, 4) if isinstance(v, float) else v for k, v in out.items()}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--resolutions", default="56,84")
    parser.add_argument("--methods", default="protonets,maml")
    args = parser.parse_args()
    report = {}
    for method in args.methods.split(","):
        for resolution in (int(r) for r in args.resolutions.split(",")):
            for way in (5, 10):
                name = f"{method}-{resolution}-{way}way"
                report[name] = measure(method, resolution, way, args.repeats)
                print(name, report[name], flush=True, file=sys.stderr)
    print(json.dumps(report, indent=1))


if __name__ == "__main__":
    main()
