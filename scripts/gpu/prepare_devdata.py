"""Write .devdata/ for a device call: a model, every 10th test image and 20 evenly spaced train images of
a benchmark, each folder with truth.json (the labels' entries, for bench_posterior's --truth).

    python scripts/gpu/prepare_devdata.py data/fsclvr-lo data/models/fsclvr-lo [.devdata]
"""
import json
import shutil
import sys
from pathlib import Path

import numpy as np

dataset, model = Path(sys.argv[1]), Path(sys.argv[2])
out = Path(sys.argv[3] if len(sys.argv) > 3 else ".devdata")
shutil.rmtree(out, ignore_errors=True)
shutil.copytree(model, out / "model", ignore=shutil.ignore_patterns("snapshots.npz", "loss_curve.csv"))
images = json.load(open(dataset / "labels.json"))["images"]
for split, folder, picks in (("test", "images", None), ("train", "train", 20)):
    rows = [r for r in images if r["split"] == split]
    chosen = rows[::10] if picks is None else [rows[int(i)] for i in np.linspace(0, len(rows) - 1, picks)]
    (out / folder).mkdir(parents=True)
    for n, row in enumerate(chosen):
        shutil.copy(dataset / row["file"], out / folder / f"{n:02d}.png")
    json.dump(chosen, open(out / folder / "truth.json", "w"))
    print(split, len(chosen), "images")
