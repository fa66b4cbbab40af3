"""Does Geweke's check see a colour move whose way back ignores the tinted fields' loading? A control.

Under tinted shading fields (:mod:`mitsuba_p3.fit.fields`) the colour's conditional depends on the colour
itself, so the colour move builds its way back on the proposal's loading
(:meth:`~mitsuba_p3.infer.material_moves.MaterialMoves._coupled_colour_move`). ``--variant broken`` makes
that move, for this run only, take the forward conditional for the way back (as if the
loading did not depend on the colour); ``right`` runs the product's move. Each prints one JSON line: the
successive-conditional check of the material update on one shape hypothesis, images simulated from the
fields' form (:func:`mitsuba_p3.evaluate.geweke.geweke_check`).

    python experiments/geweke_tinted_control.py --model data/models/dark-tinted --variant broken --chains 400 --steps 20
"""
from __future__ import annotations

import argparse
import json


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", required=True)
    parser.add_argument("--variant", choices=("right", "broken"), default="right")
    parser.add_argument("--resolution", default="60x80")
    parser.add_argument("--hypothesis", type=int, default=1, help="0 sphere, 1 cube, 2 cylinder")
    parser.add_argument("--chains", type=int, default=400)
    parser.add_argument("--steps", type=int, default=20)
    args = parser.parse_args()
    from mitsuba_p3.evaluate.geweke import geweke_check
    from mitsuba_p3.evaluate.sbc import model_core
    from mitsuba_p3.infer import material_moves

    if args.variant == "broken":
        # the moves then take the colour's forward conditional for its way back, and hand the weights' move the
        # Gram of the colour before the move (a fixed proposal for the weights, so that move stays exact):
        # only the colour move is wrong
        material_moves.MaterialMoves._tinted = property(lambda self: False)
    core = model_core(args.model, "jax", tuple(int(v) for v in args.resolution.split("x")), "fields")
    result = geweke_check(core, args.hypothesis, ("material",), args.chains, args.steps, 0)
    print(json.dumps({"variant": args.variant, "model": args.model, **result.summary()}))


if __name__ == "__main__":
    main()
