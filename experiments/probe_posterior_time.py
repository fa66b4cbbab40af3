"""Where a P3 posterior's seconds go: Mitsuba's renders against everything else, once compiled.

Samples the default P3 posterior (``infer``'s SMC under the model's default noise form) of each
image in turn in one process, and prints per image its wall-clock seconds and the seconds spent
inside the Mitsuba renderer's callbacks (``render``: colour renders; ``bases``: the material bases
that the material updates render), how many callbacks ran and how many scenes they rendered. The
first image also pays the process's compilation (JAX compiles programs with host callbacks in
every process: its persistent cache does not keep them); the images after it show the steady
state an evaluation worker runs at. What is neither render nor compilation is the JAX side of the
likelihood (the shading fields' linear algebra, the moves' arithmetic) and the host between calls.

    python experiments/probe_posterior_time.py data/models/fsclvr-fields3 \\
        data/fsclvr-lo/test/large-brown-rubber-sphere/0.png data/fsclvr-lo/test/large-brown-rubber-sphere/1.png

``--rounds 1`` samples with one round of runs (``SMCConfig.rounds``); run it with nothing else on
the cores, or say what shared them.
"""
from __future__ import annotations

import argparse
import time
from pathlib import Path

from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.images import read_png
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.posterior import default_likelihood, infer_image
from mitsuba_p3.infer.smc import SMCConfig
from mitsuba_p3.render import mitsuba as mitsuba_renderer


class RenderClock:
    """Seconds inside the Mitsuba renderer's ``render`` and ``render_bases`` (they run inside JAX's
    host callbacks, on XLA's threads, where a Python profiler of the main thread does not see them)."""

    def __enter__(self):
        self.reset()
        cls = mitsuba_renderer.MitsubaRenderer
        self._methods = cls.render, cls.render_bases
        cls.render = self._timed("render", cls.render)
        cls.render_bases = self._timed("bases", cls.render_bases)
        return self

    def __exit__(self, *exc):
        cls = mitsuba_renderer.MitsubaRenderer
        cls.render, cls.render_bases = self._methods

    def reset(self):
        self.seconds, self.calls, self.scenes = {"render": 0.0, "bases": 0.0}, 0, 0

    def _timed(self, name, method):
        def timed(renderer, params=None):
            begin = time.perf_counter()
            out = method(renderer, params)
            self.seconds[name] += time.perf_counter() - begin
            self.calls += 1
            self.scenes += len(next(iter(params.values()))) if params else 1
            return out
        return timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="a fitted-model folder (mitsuba-p3 fit)")
    parser.add_argument("images", type=Path, nargs="+", help="images at the model's resolution")
    parser.add_argument("--rounds", type=int, default=SMCConfig.rounds, help="SMC rounds of runs")
    args = parser.parse_args()
    fitted = FittedModel(args.model)
    likelihood = default_likelihood(fitted, "p3", noise=DEFAULT_NOISE)
    config = SMCConfig(rounds=args.rounds)
    with RenderClock() as clock:
        for number, path in enumerate(args.images):
            clock.reset()
            begin = time.perf_counter()
            infer_image(fitted, read_png(path), likelihood, config)
            total = time.perf_counter() - begin
            rendered = clock.seconds["render"] + clock.seconds["bases"]
            print(f"{path}: {total:.1f} s{' (with compilation)' if number == 0 else ''}; Mitsuba renders "
                  f"{rendered:.1f} s ({clock.seconds['render']:.1f} colour, {clock.seconds['bases']:.1f} bases; "
                  f"{100 * rendered / total:.0f}%), {clock.calls} callbacks, {clock.scenes} scenes "
                  f"({1e3 * rendered / max(clock.scenes, 1):.2f} ms per scene)", flush=True)


if __name__ == "__main__":
    main()
