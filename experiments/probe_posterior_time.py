"""Where a P3 posterior's seconds go: Mitsuba's renders against everything else, once compiled.

Samples the default P3 posterior (``infer``'s SMC under the model's default noise form) of each
image in turn in one process, and prints per image its wall-clock seconds and the seconds spent
inside the Mitsuba renderer's callbacks (``render``: colour renders; ``bases``: the material bases
that the material updates render), how many callbacks ran and how many scenes they rendered, in
all and by the renderer's resolution (the coarse wide start's renderer is the smaller). The first
image also pays the process's compilation (JAX compiles programs with host callbacks in every
process: its persistent cache does not keep them); the images after it show the steady state an
evaluation worker runs at. What is neither render nor compilation is the JAX side of the
likelihood (the shading fields' linear algebra, the moves' arithmetic) and the host between calls.

    python experiments/probe_posterior_time.py data/models/fsclvr-fields3 \\
        data/fsclvr-lo/test/large-brown-rubber-sphere/0.png data/fsclvr-lo/test/large-brown-rubber-sphere/1.png

``--rounds 1`` samples with one round of runs (``SMCConfig.rounds``); run it with nothing else on
the cores, or say what shared them. ``--threads 1`` runs as one of ``evaluate --jobs 2``'s workers does
(one Dr.Jit thread, a single-threaded XLA): its seconds are then also counted as the process's CPU
seconds, which another process on the cores does not inflate (it only delays them), so a probe can
share the machine with an evaluation and still say where a worker's seconds go. ``--profile`` also records a ``jax.profiler`` trace of the images
after the first and prints the XLA kernels and callbacks that took the most time in it, each by its
own time (less what ran nested inside it): how the JAX side's seconds were found (docs/notebook.md,
"The object's pixels from the render itself"). Match a kernel's name to its source with
``XLA_FLAGS=--xla_dump_to=DIR``'s ``*after_optimizations.txt``. ``--kernels`` prints each of the SMC's compiled
kernels' CPU seconds, less their renders (:class:`KernelClock`), and times one walk and one material update
of the last sweeps' particles alone: how the material update was found to cost three walks (docs/notebook.md,
"The material update's own arithmetic").
"""
from __future__ import annotations

import argparse
import collections
import contextlib
import gzip
import json
import os
import resource
import tempfile
import time
from pathlib import Path

import numpy as np

from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.images import read_png
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.posterior import default_likelihood, infer_image
from mitsuba_p3.infer.smc import SMCConfig
from mitsuba_p3.render import mitsuba as mitsuba_renderer


def cpu_seconds() -> float:
    """CPU seconds this process has used, every thread's, user and system."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class RenderClock:
    """Seconds inside the Mitsuba renderer's ``render`` and ``render_bases`` (they run inside JAX's
    host callbacks, on XLA's threads, where a Python profiler of the main thread does not see them),
    in wall-clock time and in the process's CPU time (with one thread, XLA waits for its callbacks, so
    the CPU spent meanwhile is the render's)."""

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
        self.cpu = 0.0
        # by the renderer's resolution (the coarse wide start renders at 1 / SMCConfig.coarse of it):
        # (height, width) -> [seconds, scenes]
        self.by_size = collections.defaultdict(lambda: [0.0, 0])

    def _timed(self, name, method):
        def timed(renderer, params=None, **options):
            begin, begin_cpu = time.perf_counter(), cpu_seconds()
            out = method(renderer, params, **options)
            seconds = time.perf_counter() - begin
            self.cpu += cpu_seconds() - begin_cpu
            self.seconds[name] += seconds
            self.calls += 1
            theta = (params or {}).get("theta")      # (B,) for a batch of scenes, a scalar for one
            scenes = len(theta) if np.ndim(theta) == 1 else 1
            self.scenes += scenes
            size = self.by_size[renderer.height, renderer.width]
            size[0] += seconds
            size[1] += scenes
            return out
        return timed


def own_times(trace: Path, top: int = 15) -> list[tuple[str, float, int]]:
    """The ``top`` event names of a perfetto trace (``jax.profiler.trace(..., create_perfetto_trace=True)``)
    by their own seconds, each event's duration less that of the events nested in it on its thread, with
    their counts."""
    events = json.load(gzip.open(trace))
    events = events["traceEvents"] if isinstance(events, dict) else events
    threads = collections.defaultdict(list)
    for event in events:
        if event.get("ph") == "X":
            threads[event.get("pid"), event.get("tid")].append(event)
    own, count = collections.Counter(), collections.Counter()
    for spans in threads.values():
        spans.sort(key=lambda e: (e["ts"], -e.get("dur", 0)))
        stack = []                                      # [event, its own time so far]
        for event in spans:
            while stack and stack[-1][0]["ts"] + stack[-1][0].get("dur", 0) <= event["ts"]:
                done, left = stack.pop()
                own[done["name"]] += left
            if stack:
                stack[-1][1] -= event.get("dur", 0)
            stack.append([event, event.get("dur", 0)])
            count[event["name"]] += 1
        for done, left in stack:
            own[done["name"]] += left
    return [(name, seconds / 1e6, count[name]) for name, seconds in own.most_common(top)]


class KernelClock:
    """CPU seconds inside each of the SMC's compiled kernels (:mod:`mitsuba_p3.infer.smc_moves`' ``Kernels``:
    ``sweeps``, ``score``, ``gradient``, ...) and of the tempering's steps, each call waited for, and the part of
    them that the Mitsuba renders of ``clock`` took: what a kernel costs on the JAX side is the difference."""

    def __init__(self, clock: RenderClock):
        self.clock = clock
        self.cpu = collections.defaultdict(float)
        self.rendering = collections.defaultdict(float)
        self.calls = collections.Counter()
        self.last = {}

    def __enter__(self):
        import functools

        from mitsuba_p3.infer import smc_moves, tempering

        self._patched = []
        original = smc_moves._kernels.__wrapped__

        @functools.lru_cache(maxsize=4)
        def kernels(*args):
            made = original(*args)
            timed = made._replace(**{name: self._timed(name, getattr(made, name))
                                     for name in made._fields if callable(getattr(made, name))})
            sweeps = timed.sweeps

            def kept(*arguments, **options):       # each kernel set's last sweeps arguments, for :meth:`split`
                self.last[made.walk] = (made, arguments)
                return sweeps(*arguments, **options)
            return timed._replace(sweeps=kept)
        self._patched.append((smc_moves, "_kernels", smc_moves._kernels))
        smc_moves._kernels = kernels
        for name in ("increments", "resample"):
            self._patched.append((tempering, name, getattr(tempering, name)))
            setattr(tempering, name, self._timed(f"tempering.{name}", getattr(tempering, name)))
        return self

    def __exit__(self, *exc):
        for module, name, value in self._patched:
            setattr(module, name, value)

    def split(self) -> list[str]:
        """One walk and one material update of each kernel set's last sweeps call, timed alone (each
        compiled and run once first): what a ``sweeps`` call's seconds are made of."""
        import jax

        lines = []
        for made, (key, particles, index, lam, tril, centres, observation, total) in self.last.values():
            shape = tuple(particles[0].shape)
            for name, run in (("walk", lambda: made.walk(key, particles, index, lam, tril, centres, observation)),
                              ("material", lambda: made.material(key, particles, index, lam, observation))):
                jax.block_until_ready(run())
                begin, rendered = cpu_seconds(), self.clock.cpu
                jax.block_until_ready(run())
                lines.append(f"    one {name} of {shape[0]} x {shape[1]} particles: CPU {cpu_seconds() - begin:.2f} s, "
                             f"{self.clock.cpu - rendered:.2f} s of it rendering")
        return lines

    def reset(self):
        self.last = {}
        self.cpu.clear()
        self.rendering.clear()
        self.calls.clear()

    def _timed(self, name, fn):
        import jax

        def timed(*args, **kwargs):
            begin, rendered = cpu_seconds(), self.clock.cpu
            out = jax.block_until_ready(fn(*args, **kwargs))
            self.cpu[name] += cpu_seconds() - begin
            self.rendering[name] += self.clock.cpu - rendered
            self.calls[name] += 1
            return out
        return timed


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="a fitted-model folder (mitsuba-p3 fit)")
    parser.add_argument("images", type=Path, nargs="+", help="images at the model's resolution")
    parser.add_argument("--rounds", type=int, default=SMCConfig.rounds, help="SMC rounds of runs")
    parser.add_argument("--threads", type=int, default=None,
                        help="render and XLA threads, as an evaluation worker's (default: one per core)")
    parser.add_argument("--kernels", action="store_true",
                        help="also print each compiled kernel's CPU seconds, rendering and not (KernelClock)")
    parser.add_argument("--profile", action="store_true",
                        help="trace the images after the first; print the kernels that took the most time")
    args = parser.parse_args()
    # XLA reads its flags when the backend starts (below, on first use)
    if args.threads:   # as evaluate's workers run (mitsuba_p3.evaluate.jobs)
        from mitsuba_p3.evaluate.jobs import SINGLE_THREAD_XLA_FLAGS, _limit_threads
        if args.threads == 1:
            os.environ["XLA_FLAGS"] = f"{os.environ.get('XLA_FLAGS', '')} {SINGLE_THREAD_XLA_FLAGS}".strip()
        _limit_threads(args.threads)
    if args.profile:   # XLA's per-kernel trace events
        os.environ["XLA_FLAGS"] = (os.environ.get("XLA_FLAGS", "") + " --xla_cpu_enable_xprof_traceme=true").strip()
    import jax

    traces = Path(tempfile.mkdtemp(prefix="probe-trace-"))
    fitted = FittedModel(args.model)
    likelihood = default_likelihood(fitted, "p3", noise=DEFAULT_NOISE)
    config = SMCConfig(rounds=args.rounds)
    with RenderClock() as clock, (KernelClock(clock) if args.kernels else contextlib.nullcontext()) as kernels:
        for number, path in enumerate(args.images):
            clock.reset()
            if kernels:
                kernels.reset()
            begin, begin_cpu = time.perf_counter(), cpu_seconds()
            if args.profile and number > 0:
                with jax.profiler.trace(str(traces / str(number)), create_perfetto_trace=True):
                    infer_image(fitted, read_png(path), likelihood, config)
            else:
                infer_image(fitted, read_png(path), likelihood, config)
            total, total_cpu = time.perf_counter() - begin, cpu_seconds() - begin_cpu
            rendered = clock.seconds["render"] + clock.seconds["bases"]
            print(f"{path}: {total:.1f} s{' (with compilation)' if number == 0 else ''}; Mitsuba renders "
                  f"{rendered:.1f} s ({clock.seconds['render']:.1f} colour, {clock.seconds['bases']:.1f} bases; "
                  f"{100 * rendered / total:.0f}%), {clock.calls} callbacks, {clock.scenes} scenes "
                  f"({1e3 * rendered / max(clock.scenes, 1):.2f} ms per scene)", flush=True)
            print(f"    CPU {total_cpu:.1f} s, of it in Mitsuba's renders {clock.cpu:.1f} s "
                  f"({100 * clock.cpu / max(total_cpu, 1e-9):.0f}%)", flush=True)
            for (height, width), (seconds, scenes) in sorted(clock.by_size.items()):
                print(f"    renderer {height}x{width}: {seconds:.1f} s, {scenes} scenes "
                      f"({1e3 * seconds / max(scenes, 1):.2f} ms per scene)", flush=True)
            if kernels:
                for name, seconds in sorted(kernels.cpu.items(), key=lambda item: -item[1]):
                    print(f"    kernel {name}: CPU {seconds:.1f} s in {kernels.calls[name]} calls, "
                          f"{kernels.rendering[name]:.1f} s of it rendering, {seconds - kernels.rendering[name]:.1f} s not",
                          flush=True)
                print("\n".join(kernels.split()), flush=True)
            for trace in sorted((traces / str(number)).glob("**/perfetto_trace.json.gz")):
                for name, seconds, calls in own_times(trace):
                    print(f"    {seconds:7.2f} s {calls:7d} x  {name[:100]}")


if __name__ == "__main__":
    main()
