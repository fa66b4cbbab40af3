"""Do XLA's YNNPACK fusions change a posterior? The same images sampled with and without them.

Samples the default P3 posterior of each image twice, each time in a fresh process set up as one of
``evaluate --jobs 2``'s workers (one Dr.Jit thread, a single-threaded XLA): once under XLA's default
(``MITSUBA_P3_YNNPACK=on``) and once under the package's ``--xla_cpu_experimental_ynn_fusion_type=``
(:data:`mitsuba_p3.NO_YNNPACK`). Prints per image the largest difference of the shape probabilities,
of the position draws and of the colour draws' means. The arithmetic differs only by float32
rounding, so the draws are either equal to rounding or, once a rounding difference flips one
acceptance, as different as another seed's (docs/notebook.md, "XLA's YNNPACK fusions and a
posterior's seconds").

    python experiments/probe_xla_flags.py data/models/fsclvr-tinted data/fsclvr-lo/test/*/2.png
"""
from __future__ import annotations

import argparse
import os
import subprocess
import sys
import tempfile
from pathlib import Path

import numpy as np

_SAMPLE = """
import sys, numpy as np
from mitsuba_p3.evaluate.jobs import _limit_threads
_limit_threads(1)
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.images import read_png
from mitsuba_p3.infer.likelihood import DEFAULT_NOISE
from mitsuba_p3.infer.posterior import default_likelihood, infer_image
from mitsuba_p3.infer.smc import SMCConfig
fitted = FittedModel(sys.argv[2])
likelihood = default_likelihood(fitted, "p3", noise=DEFAULT_NOISE)
out = {}
for i, path in enumerate(sys.argv[3:]):
    posterior = infer_image(fitted, read_png(path), likelihood, SMCConfig()).idata.posterior
    for name in ("class_probabilities", "shift", "colour"):
        out[f"{i}/{name}"] = np.asarray(posterior[name])
np.savez(sys.argv[1], **out)
"""


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("model", type=Path, help="a fitted-model folder (mitsuba-p3 fit)")
    parser.add_argument("images", type=Path, nargs="+", help="images at the model's resolution")
    args = parser.parse_args()
    folder = Path(tempfile.mkdtemp(prefix="probe-xla-"))
    runs = {}
    for name, ynnpack in (("default", "on"), ("without", "off")):
        env = {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"}
        env["MITSUBA_P3_YNNPACK"] = ynnpack
        out = folder / f"{name}.npz"
        subprocess.run([sys.executable, "-c", _SAMPLE, str(out), str(args.model), *map(str, args.images)],
                       env=env, check=True)
        runs[name] = np.load(out)
    a, b = runs["default"], runs["without"]
    for i, path in enumerate(args.images):
        shape = np.abs(a[f"{i}/class_probabilities"] - b[f"{i}/class_probabilities"]).max()
        shift = np.abs(a[f"{i}/shift"] - b[f"{i}/shift"]).max()
        colour = np.abs(a[f"{i}/colour"].mean(axis=(0, 1)) - b[f"{i}/colour"].mean(axis=(0, 1))).max()
        print(f"{path}: shape probabilities {shape:.2g}, position draws {shift:.2g}, colour means {colour:.2g}",
              flush=True)


if __name__ == "__main__":
    main()
