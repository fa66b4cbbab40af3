"""Would the image's own light mend a shape the fields miss? The fitted lights turned about the object.

CLEVR-like worlds move their lights from image to image; the model renders every image under the fitted
lights. For one image and a posterior saved by ``mitsuba-p3 infer``, this turns all the fitted lights
together about the vertical axis through the object's labelled position, in steps of ``--step`` degrees,
and at each turn scores under the default likelihood: the truth (its labelled pose, the best of the fit's
gray and brown materials and the true one darkened), and the run's best draw of each shape class. A shape
whose best draw leads only under some turn is one a latent light per image would let the model see.

    python experiments/probe_light_turn.py data/fsclvr-lo --model data/models/fsclvr-fields3 \\
        --image large-gray-rubber-sphere/5 --posterior RUN/posterior.nc [--step 30] [--noise fields]
"""
from __future__ import annotations

import argparse
import copy
import json

import numpy as np

from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.shapes import SHAPES
from probe_fields_power import add_case_arguments, load_case, position_of


def main() -> None:
    import jax
    import jax.numpy as jnp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    add_case_arguments(parser)
    parser.add_argument("--step", type=int, default=30, help="degrees between turns")
    parser.add_argument("--noise", default="fields")
    args = parser.parse_args()
    dataset, _, image, truth, draws, kappa = load_case(args, parser)
    for turn in range(0, 360, args.step):
        fitted = FittedModel(args.model)                  # a fresh model per turn: its scene is replaced below
        scene = copy.deepcopy(fitted.scene())
        c, s = np.cos(np.radians(turn)), np.sin(np.radians(turn))
        centre = np.array([*truth["shift"], 0.0])
        for light in scene.lights:
            p = np.asarray(light.position, float) - centre
            light.position = centre + np.array([c * p[0] - s * p[1], s * p[0] + c * p[1], p[2]])
        fitted.scene = lambda scene=scene: scene          # this core renders under the turned lights
        core = PosteriorCore(fitted, default_likelihood(fitted, "p3", noise=args.noise), "mitsuba", *dataset.resolution)
        observation = core.observe(image, core.window_for(image, SCORING_WINDOW))
        score = jax.jit(jax.vmap(lambda z: core.log_likelihood(z, observation)))
        candidates = [position_of(fitted.prior, {**truth, **{k: np.asarray(v, np.float32) for k, v in m.items()}})
                      for key, m in fitted.materials.items() if key.startswith(("gray", "brown"))]
        candidates.append(position_of(fitted.prior, {**truth, "colour": np.asarray(truth["colour"]) * 0.6}))
        of_truth = np.asarray(score(jnp.asarray(np.stack(candidates), jnp.float32)))
        of_draws = np.asarray(score(jnp.asarray(draws, jnp.float32)))
        print(json.dumps({"turn_degrees": turn, "truth, best material": round(float(of_truth.max()), 1),
                          **{f"best {shape} draw": round(float(of_draws[kappa == k].max()), 1)
                             for k, shape in enumerate(SHAPES) if np.any(kappa == k)}}), flush=True)


if __name__ == "__main__":
    main()
