"""How a posterior's colour is read: the colour centres of the fit's rule and of the rule evaluate learns from
train posteriors, beside the median chromaticity of chosen classes' test posteriors and the name each rule gives.

    python experiments/probe_colour_reading.py data/dark-lo out/eval-dark-white data/models/dark-white

(Written for dark's colour regression, thirtieth session: results/eval-dark-white; the classes are in the code.)
"""
import sys
from pathlib import Path
import numpy as np
from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.evaluate.jobs import CachedPosterior, posterior_path, PosteriorMisfits
from mitsuba_p3.fit.attributes import rules_for, median_chromaticity
from mitsuba_p3.fit.model import FittedModel
from mitsuba_p3.evaluate.run import rules_with_train_posteriors
ds, run, model = load_dataset(sys.argv[1]), Path(sys.argv[2]), Path(sys.argv[3])
misfits = PosteriorMisfits(ds, model)
fit = rules_for(FittedModel(model), ds); learnt = rules_with_train_posteriors(fit, ds, run, "p3", misfits)
for name, r in (("fit", fit), ("learnt", learnt)):
    print(name, [(n, k, np.round(a, 3).tolist()) for n, k, a in zip(r.colour_names, r.colour_kinds or [None]*99, r.colour_albedos) if n in ("green", "gray", "brown", "yellow")])
for s in ds.split("test"):
    if s.cls.name in ("small-green-rubber-cube", "small-brown-rubber-cylinder"):
        post = CachedPosterior.load(posterior_path(run, "p3", s.index), 100000)
        c = median_chromaticity(post.program.samples)
        print(s.index, s.cls.name, np.round(c, 3).tolist(), fit.colour_name(c), learnt.colour_name(c))
