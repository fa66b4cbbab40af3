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

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.fit.model import FittedModel, shot_params
from mitsuba_p3.fit.noise import SCORING_WINDOW
from mitsuba_p3.infer.model import PosteriorCore
from mitsuba_p3.infer.posterior import default_likelihood
from mitsuba_p3.shapes import SHAPES


def main() -> None:
    import arviz as az
    import jax
    import jax.numpy as jnp

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("dataset")
    parser.add_argument("--model", required=True)
    parser.add_argument("--image", required=True, help="CLASS/NUMBER of the test split")
    parser.add_argument("--posterior", required=True, help="posterior.nc of mitsuba-p3 infer on that image")
    parser.add_argument("--step", type=int, default=30, help="degrees between turns")
    parser.add_argument("--noise", default="fields")
    args = parser.parse_args()

    dataset = load_dataset(args.dataset)
    shots = [s for s in dataset.split("test") if f"{s.class_name}/{s.file.stem}" == args.image]
    if not shots:
        parser.error(f"no image {args.image} in {args.dataset}'s test split")
    image = dataset.image(shots[0])
    posterior = az.from_netcdf(args.posterior).posterior
    draws = posterior["z"].values.reshape(-1, posterior["z"].shape[-1])
    kappa = posterior["kappa"].values.reshape(-1)
    for turn in range(0, 360, args.step):
        fitted = FittedModel(args.model)
        truth = shot_params(shots[0], fitted.materials)
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

        def position(params: dict) -> np.ndarray:
            probabilities = np.full(len(SHAPES), 0.01)
            probabilities[int(params["kappa"])] = 1.0 - 0.01 * (len(SHAPES) - 1)
            return fitted.prior.unconstrain({**{k: np.asarray(v) for k, v in params.items()},
                                             "class_probabilities": probabilities})

        candidates = [position({**truth, **{k: np.asarray(v, np.float32) for k, v in m.items()}})
                      for key, m in fitted.materials.items() if key.startswith(("gray", "brown"))]
        candidates.append(position({**truth, "colour": np.asarray(truth["colour"]) * 0.6}))
        of_truth = np.asarray(score(jnp.asarray(np.stack(candidates), jnp.float32)))
        of_draws = np.asarray(score(jnp.asarray(draws, jnp.float32)))
        print(json.dumps({"turn_degrees": turn, "truth, best material": round(float(of_truth.max()), 1),
                          **{f"best {shape} draw": round(float(of_draws[kappa == k].max()), 1)
                             for k, shape in enumerate(SHAPES) if np.any(kappa == k)}}), flush=True)


if __name__ == "__main__":
    main()
