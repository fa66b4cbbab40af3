"""The logic of choosing knobs on train classes and of the paper-layout tables (the heavy parts are the
tested library calls)."""
from __future__ import annotations

import json

import numpy as np
import pytest

from mitsuba_p3 import reproduce as tables
from mitsuba_p3.concepts import CONTINUOUS, DistanceConfig, ProtoProgram
from mitsuba_p3.evaluate import held_out_accuracy


def load_script(name: str):
    """A script of ``scripts/`` (the tools) or ``experiments/`` (the lab) imported as a module (its ``main``
    is not run)."""
    import importlib.util
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    path = next(p for p in (root / "scripts" / f"{name}.py", root / "experiments" / f"{name}.py") if p.is_file())
    if str(path.parent) not in sys.path:       # a script may import its neighbours (probe_supersampling)
        sys.path.insert(0, str(path.parent))
    spec = importlib.util.spec_from_file_location(name, path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def program(rng, centre: float, spread: float, n: int = 200) -> ProtoProgram:
    samples = {name: centre + spread * rng.standard_normal((n, 3 if name in ("scale", "colour") else 1))
               for name in CONTINUOUS}
    samples["class"] = np.zeros(n, int)
    return ProtoProgram(samples)


@pytest.mark.parametrize("spread, expect_perfect", [(0.01, True), (10.0, False)])
def test_held_out_accuracy_separates_distinct_classes_only(spread, expect_perfect):
    """Well separated classes are always told apart; classes lost in their own noise are not."""
    rng = np.random.default_rng(0)
    programs = {f"c{i}": [program(rng, float(i), spread), program(rng, float(i), spread)] for i in range(12)}
    accuracy = held_out_accuracy(programs, 5, 20, 0, DistanceConfig(samples=100))
    assert (accuracy == 1.0) == expect_perfect
    assert 0.0 <= accuracy <= 1.0


def test_held_out_accuracy_k_shot_episodes_and_the_kl_direction():
    """Classes whose images fall in two modes (10 apart): one shot is often in the query's other mode,
    five always cover both. Under KL(C_I || C_k) five shots then beat one; under the paper's
    KL(C_k || C_I) the merged class's draws in its other mode push every class away and five shots
    lose. A class with too few programs for the setting is refused."""
    rng = np.random.default_rng(1)
    programs = {f"c{i}": [program(rng, float(i + 10 * (j % 2)), 0.05) for j in range(6)] for i in range(10)}

    def accuracy(k_shot, direction, data=programs, episodes=40):
        return held_out_accuracy(data, 5, episodes, 0, DistanceConfig(samples=100, direction=direction), k_shot)

    one = accuracy(1, "image||class")
    assert accuracy(5, "image||class") > one + 0.1
    assert accuracy(5, "class||image") < one - 0.1
    with pytest.raises(ValueError, match="6 programs per class"):
        accuracy(5, "image||class", {**programs, "short": programs["c0"][:5]}, 1)


def result(accuracy: float, adi: float) -> dict:
    """An evaluation's results as a run's ``results.json`` holds them, every cell ``accuracy``."""
    cell = {"mean": accuracy, "half_width": 0.01, "ece": 0.1, "reliability": [[0.55, accuracy, 10], [0.9, 0.8, 0]]}
    return {"accuracy": {f"{n}-way {k}-shot": cell for n, k in tables.SETTINGS},
            "adi": {"mean": adi, "median": adi}, "attributes": {"shape_accuracy": accuracy, "images": 3}}


def test_run_names_round_trip_and_tables_keep_sigma_and_distance_runs_apart(tmp_path):
    for variant, sigma in (("fsclvr", None), ("dark", 0.1), ("ood", 0.05)):
        assert tables.parse_run_name(tables.run_name(variant, sigma)) == (variant, sigma)
    assert tables.parse_run_name("scratch") is None and tables.parse_run_name("fsclvr-sigmaX") is None

    for name, accuracy in (("fsclvr", 0.5), ("fsclvr-sigma0.1", 0.9), ("fsclvr/distance-colour+class", 0.7),
                           ("fsclvr-sigma0.1/distance-colour", 0.8), ("fsclvr/spread0", 0.6),
                           ("fsclvr/kl-class-image", 0.3), ("fsclvr/distance-colour-kl-class-image", 0.2),
                           ("fsclvr/gaussian-concepts", 0.45), ("fsclvr/kl-class-image-gaussian-concepts", 0.25)):
        (tmp_path / "runs" / name).mkdir(parents=True)
        (tmp_path / "runs" / name / "results.json").write_text(json.dumps({"results": {"p3": result(accuracy, 0.01)}}))
    # a baseline scored into runs/room, where no P3 run is (the P3 runs of a benchmark may all be fitted-noise ones)
    (tmp_path / "runs" / "room" / "baselines").mkdir(parents=True)
    (tmp_path / "runs" / "room" / "baselines" / "protonets-56.json").write_text(
        json.dumps({"model": "ProtoNets 56", **result(0.4, 0.0)}))
    found = tables.collect(tmp_path)
    assert set(found) == {("fsclvr", None, None), ("fsclvr", 0.1, None), ("fsclvr", None, "colour+class"),
                          ("fsclvr", 0.1, "colour"), ("fsclvr", None, "spread0"), ("fsclvr", None, "kl-class-image"),
                          ("fsclvr", None, "colour-kl-class-image"), ("fsclvr", None, "gaussian-concepts"),
                          ("fsclvr", None, "kl-class-image-gaussian-concepts")}
    tables.write_paper_tables(tmp_path, found)
    lines = (tmp_path / "accuracy.md").read_text().splitlines()
    assert any(line.startswith("| ProtoNets 56 | this project | - | 40.0/40.0/40.0/40.0 |") for line in lines)
    assert any(line.startswith("| P3 | this project | 50.0/50.0/50.0/50.0 |") for line in lines)
    assert any(line.startswith("| P3 (sigma 0.1) | this project | 90.0/90.0/90.0/90.0 |") for line in lines)
    assert any(line.startswith("| P3 (colour+class) | this project | 70.0/70.0/70.0/70.0 |") for line in lines)
    assert any(line.startswith("| P3 (sigma 0.1, colour) | this project | 80.0/80.0/80.0/80.0 |") for line in lines)
    assert any(line.startswith("| P3 (KL(class || image)) | this project | 30.0/30.0/30.0/30.0 |") for line in lines)
    assert any(line.startswith("| P3 (colour, KL(class || image)) | this project | 20.0/20.0/20.0/20.0 |")
               for line in lines)
    assert any(line.startswith("| P3 (no concept spread) | this project | 60.0/60.0/60.0/60.0 |") for line in lines)
    assert any(line.startswith("| P3 (Gaussian concept kernels) | this project | 45.0/45.0/45.0/45.0 |") for line in lines)
    assert any(line.startswith("| P3 (KL(class || image), Gaussian concept kernels) | this project | 25.0/25.0/25.0/25.0 |")
               for line in lines)
    assert all((tmp_path / "figures" / f"{name}.png").stat().st_size > 5000
               for name in ("accuracy", "attributes", "reliability-fsclvr"))
    adi = (tmp_path / "adi.md").read_text()
    assert "P3 (sigma 0.1) mean ADI" in adi and "colour" not in adi  # ADI does not depend on the distance


def test_a_run_is_found_by_its_record_not_its_name(tmp_path):
    """A run folder renamed (or named by hand) is tabulated as what its run.json says it is: the
    benchmark and the noise model; a record before the benchmark was kept takes it from the data set's
    labels; a folder whose record is not an evaluation's is not a run."""
    (tmp_path / "data").mkdir()
    (tmp_path / "data" / "labels.json").write_text(json.dumps({"variant": "dark"}))
    for name, record, accuracy in (
            ("my-room-try", {"benchmark": "room", "noise": "fitted", "sigma": None}, 0.7),
            ("old-record", {"dataset": str(tmp_path / "data"), "noise": "paper", "sigma": 0.35}, 0.6),
            ("fsclvr", {"benchmark": "fsclvr", "noise": "paper", "sigma": None}, 0.5)):
        (tmp_path / "runs" / name).mkdir(parents=True)
        (tmp_path / "runs" / name / "run.json").write_text(json.dumps({"format": "mitsuba-p3-evaluation", **record}))
        (tmp_path / "runs" / name / "results.json").write_text(json.dumps({"results": {"p3": result(accuracy, 0.01)}}))
    (tmp_path / "runs" / "room-fitted").mkdir()
    (tmp_path / "runs" / "room-fitted" / "run.json").write_text(json.dumps({"format": "something else"}))
    (tmp_path / "runs" / "room-fitted" / "results.json").write_text(json.dumps({"results": {"p3": result(0.1, 0.01)}}))
    found = tables.collect(tmp_path)
    assert {k: v["p3"]["accuracy"]["5-way 1-shot"]["mean"] for k, v in found.items()} == {
        ("room", "fitted", None): 0.7, ("dark", 0.35, None): 0.6, ("fsclvr", None, None): 0.5}


def test_tables_only_rewrites_the_tables_from_run_folders_and_refuses_a_folder_without_runs(tmp_path):
    """``reproduce --tables-only``: the tables of a results folder copied without its posteriors, a baseline
    scored since included; nothing to tabulate is one error line."""
    import subprocess
    import sys

    (tmp_path / "runs" / "dark-fitted").mkdir(parents=True)
    (tmp_path / "runs" / "dark-fitted" / "results.json").write_text(json.dumps({"results": {"p3": result(0.9, 0.01)}}))
    (tmp_path / "runs" / "dark" / "baselines").mkdir(parents=True)
    (tmp_path / "runs" / "dark" / "baselines" / "maml-84.json").write_text(
        json.dumps({"model": "MAML 84", **result(0.7, 0.0)}))
    command = [sys.executable, "-m", "mitsuba_p3.cli", "reproduce", "--tables-only", "--out"]
    done = subprocess.run(command + [str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    lines = (tmp_path / "accuracy.md").read_text().splitlines()
    assert any(line.startswith("| P3 (fitted noise) | this project | - | - | 90.0/90.0/90.0/90.0 |") for line in lines)
    assert any(line.startswith("| MAML 84 | this project | - | - | 70.0/70.0/70.0/70.0 |") for line in lines)
    assert (tmp_path / "figures" / "accuracy.png").is_file() and (tmp_path / "adi.md").is_file()

    (tmp_path / "empty").mkdir()
    refused = subprocess.run(command + [str(tmp_path / "empty")], capture_output=True, text=True, timeout=300)
    assert refused.returncode == 2 and refused.stderr.strip().startswith("error:") and "nothing to tabulate" in refused.stderr
    assert len(refused.stderr.strip().splitlines()) == 1 and not (tmp_path / "empty" / "accuracy.md").exists()


@pytest.mark.parametrize("shift", [np.full((100, 2), 0.01), np.c_[np.linspace(0, 0.01, 100), np.zeros(100)],
                                   np.full((1, 2), 0.01)])
def test_translation_figure_survives_draws_that_do_not_move(tmp_path, shift):
    """Short chains on a large image gave a singular covariance in the figure step, after posterior.nc."""
    from mitsuba_p3.plots import translation_contours

    assert translation_contours(shift, tmp_path / "t.png").stat().st_size > 1000


def test_reproduce_generates_at_the_asked_resolution(tmp_path, monkeypatch):
    """``--resolution`` reaches every generated benchmark (ood's fsclvr too); a bad one is refused up front."""
    import mitsuba_p3.benchmarks.generate as generate_module
    from mitsuba_p3.errors import ConfigError

    calls = []
    monkeypatch.setattr(generate_module, "generate", lambda variant, out, **kw: calls.append((variant, kw["resolution"])))
    monkeypatch.setattr("mitsuba_p3.fit.model.fit_model", lambda *a, **kw: calls.append(("fit", None)))
    folder, model = tables.prepare(tmp_path, "ood", resolution=(120, 160))
    assert (folder, model) == (tmp_path / "ood", tmp_path / "models" / "fsclvr")
    assert calls == [("ood", (120, 160)), ("fsclvr", (120, 160)), ("fit", None)]
    with pytest.raises(ConfigError, match="resolution"):
        tables.ReproduceConfig(resolution=(4, 160))


@pytest.mark.slow
def test_train_baselines_trains_scores_and_resumes(tmp_path):
    """mitsuba-p3 baseline train-all trains a baseline to its cap, scores it into the run folder, and a
    rerun resumes: nothing is trained or scored again."""
    import subprocess
    import sys
    from pathlib import Path

    from mitsuba_p3.benchmarks.generate import generate

    generate("fsclvr", tmp_path / "data" / "fsclvr", seed=2, size="small", resolution=(30, 40), spp=4)
    command = [sys.executable, "-m", "mitsuba_p3.cli", "baseline", "train-all", "--data", str(tmp_path / "data"),
               "--out", str(tmp_path / "out"),
               "--benchmarks", "fsclvr", "--methods", "protonets", "--resolutions", "56", "--iterations", "4",
               "--episodes", "3"]
    first = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert first.returncode == 0, first.stderr
    line = json.loads(first.stdout.strip().splitlines()[-1])
    assert line["baseline"] == "fsclvr-protonets-56" and line["iterations"] == 4
    result = tmp_path / "out" / "runs" / "fsclvr" / "baselines" / "protonets-56.json"
    written = result.stat().st_mtime_ns
    again = subprocess.run(command, capture_output=True, text=True, timeout=900)
    assert again.returncode == 0, again.stderr
    assert json.loads(again.stdout.strip().splitlines()[-1])["iterations"] == 4
    assert result.stat().st_mtime_ns == written


def test_probe_resolution_reads_only_the_rendered_train_images(tmp_path):
    """experiments/probe_resolution.py's view of a benchmark still rendering: the train images on disk,
    with their labels; test images and missing train images left out, the scene file kept."""
    probe = load_script("probe_resolution")
    root = tmp_path / "bench"
    records = [{"file": f"{split}/c/{i}.png", "split": split} for split in ("train", "test") for i in range(3)]
    (root / "train" / "c").mkdir(parents=True)
    (root / "test" / "c").mkdir(parents=True)
    for record in records[:2] + records[3:]:                  # train/c/2.png is not rendered yet
        (root / record["file"]).write_bytes(b"png")
    (root / "labels.json").write_text(json.dumps({"format": "x", "images": records}))
    (root / "scene.xml").write_text("<scene/>")
    (tmp_path / "views").mkdir()
    view = probe.train_view(root, tmp_path / "views")
    kept = json.loads((view / "labels.json").read_text())["images"]
    assert [r["file"] for r in kept] == ["train/c/0.png", "train/c/1.png"]
    assert (view / "train" / "c" / "1.png").read_bytes() == b"png" and not (view / "test").exists()
    assert (view / "scene.xml").is_file()


def test_object_box_frames_what_the_object_changes():
    """The posterior figure's zoom: a box with the image's aspect around the pixels where the render
    differs from the empty floor, inside the image; none when nothing differs or the object is most
    of the image."""
    from mitsuba_p3.plots import object_box

    empty = np.full((120, 160, 3), 0.4)
    render = empty.copy()
    render[50:58, 150:158] = 0.9                 # a small object near the right edge
    top, left, height, width = object_box(render, empty)
    assert 0 <= top <= 50 and top + height >= 58 and 0 <= left <= 150 and left + width >= 158
    assert left + width <= 160 and abs(width / height - 160 / 120) < 0.05 and height >= 30
    assert object_box(empty, empty) is None
    render[10:110, 10:150] = 0.9
    assert object_box(render, empty) is None


def test_compare_reproductions_reads_two_output_folders(tmp_path, capsys):
    """scripts/compare_reproductions.py: the cells both folders hold, their difference in points, the
    share of images whose decided attributes agree, both ADIs; a folder without tables is refused."""
    compare = load_script("compare_reproductions")
    head = "benchmark,model,sigma,distance,setting,accuracy,half_width_95,ece,paper\n"
    attributes_head = "model,query,shape_decided,material_decided,size_decided,colour_decided\n"
    for name, accuracy, shape in (("a", 0.90, "cube"), ("b", 0.88, "sphere")):
        folder = tmp_path / name
        (folder / "runs" / "room-fitted").mkdir(parents=True)
        (folder / "accuracy.csv").write_text(head + f"room,p3,fitted,paper,5-way 1-shot,{accuracy},0.03,0.1,0.92\n"
                                             + "room,maml,,,5-way 1-shot,0.5,0.1,,\n")
        (folder / "adi.csv").write_text("benchmark,model,sigma,mean_adi_m\nroom,p3,fitted,0.01\n")
        (folder / "runs" / "room-fitted" / "attributes.csv").write_text(
            attributes_head + f"p3,1,{shape},metal,large,red\np3,2,cube,metal,large,red\n")
    compare.main([str(tmp_path / "a"), str(tmp_path / "b")])
    printed = capsys.readouterr().out
    assert "| room | p3 | fitted | paper | 5-way 1-shot | 90.0 | 88.0 | -2.0 | 3.0 |" in printed
    assert "maml" not in printed
    assert "| room-fitted | p3 | 2 | 50.0% | 100.0% | 100.0% | 100.0% |" in printed
    assert "| room | p3 | fitted | 0.0100 | 0.0100 |" in printed
    (tmp_path / "c").mkdir()
    with pytest.raises(SystemExit):
        compare.main([str(tmp_path / "a"), str(tmp_path / "c")])


def test_compare_evaluations_pairs_two_runs_episode_by_episode(tmp_path, capsys):
    """scripts/compare_evaluations.py: both accuracies and B - A per episode with its bootstrap interval; two
    runs of other data sets, or whose episodes differ, are refused."""
    compare = load_script("compare_evaluations")
    head = "n_way,k_shot,episode,query,truth,predicted,confidence,p_true,model\n"
    for name, wrong in (("a", {0, 1}), ("b", {0})):       # B gets episode 1's query right, A does not
        folder = tmp_path / name
        folder.mkdir()
        (folder / "run.json").write_text(json.dumps({"labels_digest": "same"}))
        rows = [f"5,1,{e},{10 + e},0,{1 if e in wrong else 0},0.9,0.1,p3\n" for e in range(4)]
        (folder / "predictions.csv").write_text(head + "".join(rows) + "5,1,0,10,0,0,0.9,0.9,maml\n")
        (folder / "attributes.csv").write_text("model,query,shape_true,shape_decided,material_true,material_decided,"
                                               "size_true,size_decided,colour_true,colour_decided\n"
                                               "p3,10,cube,cube,metal,rubber,large,large,red,red\n")
    compare.main([str(tmp_path / "a"), str(tmp_path / "b")])
    printed = capsys.readouterr().out
    assert "5-way 1-shot:  50.0 ->  75.0, paired difference +25.0" in printed
    assert "material 0.0 -> 0.0" in printed and "shape 100.0 -> 100.0" in printed
    assert "posteriors of" not in printed                 # no cached posteriors: nothing said of them
    # cached posteriors: image 1's modal shape moves from sphere to cube, image 2's shares by 0.25 only
    for name, classes in (("a", ([0, 0, 0, 1], [2, 2, 2, 2])), ("b", ([1, 1, 1, 0], [2, 2, 2, 1]))):
        folder = tmp_path / name / "posteriors" / "p3"
        folder.mkdir(parents=True)
        for image, (drawn, gap) in enumerate(zip(classes, (2.0, 12.0)), start=1):
            np.savez(folder / f"{image:05d}.npz", sample_class=np.array(drawn, np.int8), island_gap=np.float64(gap),
                     particles_temperatures=np.int64(15 + image), seconds=np.float64(10.0 * image))
    compare.main([str(tmp_path / "a"), str(tmp_path / "b")])
    printed = capsys.readouterr().out
    assert "posteriors of 2 images: modal shape the same in 50.0%, shape shares moved by > 0.3 on 1: [1]" in printed
    assert "A: island gap median 7.00, p90 11.0, > 10 nats 50%; temperatures median 16; seconds per posterior " \
           "mean 15.0" in printed
    (tmp_path / "b" / "predictions.csv").unlink()          # a run still sampling: its posteriors alone
    compare.main([str(tmp_path / "a"), str(tmp_path / "b"), "--posteriors-only"])
    printed = capsys.readouterr().out
    assert printed.startswith("posteriors of 2 images") and "paired difference" not in printed
    (tmp_path / "b" / "predictions.csv").write_text((tmp_path / "a" / "predictions.csv").read_text())
    (tmp_path / "b" / "run.json").write_text(json.dumps({"labels_digest": "other"}))
    with pytest.raises(SystemExit):
        compare.main([str(tmp_path / "a"), str(tmp_path / "b")])
    (tmp_path / "b" / "run.json").write_text(json.dumps({"labels_digest": "same"}))
    moved = (tmp_path / "b" / "predictions.csv").read_text().replace("5,1,3,13,", "5,1,3,14,")
    (tmp_path / "b" / "predictions.csv").write_text(moved)
    with pytest.raises(SystemExit):
        compare.main([str(tmp_path / "a"), str(tmp_path / "b")])


def test_probe_gap_causes_tells_a_run_that_settled_short_from_the_estimates_noise(tmp_path):
    """experiments/probe_gap_causes.py: the leader's runs' best-log-likelihood spread and its margin over the
    runner-up hypothesis, read from a cached posterior."""
    probe = load_script("probe_gap_causes")
    path = tmp_path / "00001.npz"
    loglik = np.array([[10.0, 50.0], [12.0, 49.0], [5.0, 20.0], [1.0, 30.0]])      # runs (rows) x particles
    np.savez(path, island_gap=np.float64(12.0), particles_index=np.array([0, 0, 1, 1]),
             particles_log_evidence=np.array([40.0, 28.0, 10.0, 25.0]), particles_loglikelihood=loglik)
    causes = probe.gap_causes(path)
    assert causes == {"gap": 12.0, "best_spread": 1.0, "margin": 15.0}
    np.savez(path, island_gap=np.float64(0.0), particles_index=np.array([2]),
             particles_log_evidence=np.array([3.0]), particles_loglikelihood=loglik[:1])
    assert probe.gap_causes(path)["margin"] == float("inf")


def test_select_np3_start_takes_train_images_round_robin_over_classes():
    """experiments/select_np3_start.py's images: train shots only, first shots of every class before any
    second shot, as many as asked (or all there are)."""
    from types import SimpleNamespace

    script = load_script("select_np3_start")
    shots = [SimpleNamespace(index=i, cls=c, split="train") for i, c in enumerate("aabbbc")]
    dataset = SimpleNamespace(split=lambda name: shots if name == "train" else [])
    assert [s.index for s in script.train_images(dataset, 4)] == [0, 2, 5, 1]
    assert sorted(s.index for s in script.train_images(dataset, 100)) == list(range(6))


def test_only_the_headline_run_writes_the_benchmarks_posterior_figure():
    """A reproduction under the paper's likelihood (or another sigma) names its posterior figure after
    its run, so it does not overwrite the headline run's ``posterior-V.png``."""
    from mitsuba_p3.infer.likelihood import DEFAULT_NOISE

    assert tables.posterior_figure_name("room", DEFAULT_NOISE) == "posterior-room.png"
    assert tables.posterior_figure_name("room", "fitted") == "posterior-room-fitted.png"
    assert tables.posterior_figure_name("room", None) == "posterior-room-paper.png"
    assert tables.posterior_figure_name("dark", 0.35) == "posterior-dark-sigma0.35.png"
    assert tables.posterior_figure_name("ood", "robust") == "posterior-ood-robust.png"


def test_pooling_probe_place_correlation_sees_place_and_only_place():
    """experiments/probe_baseline_pooling.py: an embedding that is where the object stands correlates 1
    with the floor distance; one that does not see the place is not ordered by it. Images are
    embedded in one batch, so classes come back in the order they went in."""
    script = load_script("probe_baseline_pooling")
    rng = np.random.default_rng(0)
    positions = {name: [np.array([*rng.uniform(-0.08, 0.08, 2), 0.0]) for _ in range(6)] for name in "ab"}
    # each "image" carries its object's (x, y) in its first two pixels and noise elsewhere
    held = {name: np.stack([np.pad(p[:2], (0, 6)) + [0, 0, *rng.random(6)] for p in positions[name]])
            for name in "ab"}
    where = lambda params, images: images[:, :2]           # noqa: E731
    look = lambda params, images: images[:, 2:]            # noqa: E731
    assert script.place_correlation(where, None, held, positions) == pytest.approx(1.0)
    assert abs(script.place_correlation(look, None, held, positions)) < 0.5


def test_tracer_benchmark_carries_the_scene_by_a_rotation_and_refuses_a_folder_without_tamayo(tmp_path):
    """scripts/bench_tracers.py: our z-up frame goes to tamayo's y-up one by a rotation (lengths, angles
    and handedness kept), and a --authors folder that holds no tamayo/ is refused with the fix."""
    import subprocess
    import sys
    from pathlib import Path

    scripts = Path(__file__).resolve().parents[1] / "scripts"
    sys.path.insert(0, str(scripts))
    from bench_tracers import _frame

    basis = _frame(np.eye(3))                 # rows: where x, y and z go
    np.testing.assert_allclose(basis @ basis.T, np.eye(3), atol=1e-7)
    assert np.isclose(np.linalg.det(basis), 1.0)
    np.testing.assert_allclose(_frame([0.0, 0.0, 1.0]), [0.0, 1.0, 0.0])      # up stays up
    done = subprocess.run([sys.executable, str(scripts / "bench_tracers.py"), "--authors", str(tmp_path)],
                          capture_output=True, text=True, timeout=120)
    assert done.returncode != 0 and "holds no tamayo" in done.stderr


def test_the_posterior_time_probe_counts_renders_and_puts_the_renderer_back(monkeypatch):
    """experiments/probe_posterior_time.py's clock: every render call and scene counted, colour and bases apart
    and by the renderer's resolution (the coarse start's is the smaller), and the renderer's own methods
    restored when it is done."""
    from types import SimpleNamespace

    import numpy as np

    from mitsuba_p3.render import mitsuba as mitsuba_renderer

    def render(renderer, params=None, objects=False):
        image = np.zeros((np.size(params["theta"]), 2, 2, 3))
        return (image, np.zeros(image.shape[:3], bool)) if objects else image

    def render_bases(renderer, params=None, objects=False):
        return np.zeros((len(params["theta"]), 2, 2, 4, 3))

    monkeypatch.setattr(mitsuba_renderer.MitsubaRenderer, "render", render)
    monkeypatch.setattr(mitsuba_renderer.MitsubaRenderer, "render_bases", render_bases)
    probe = load_script("probe_posterior_time")
    full, coarse = SimpleNamespace(height=120, width=160), SimpleNamespace(height=60, width=80)
    with probe.RenderClock() as clock:
        cls = mitsuba_renderer.MitsubaRenderer
        cls.render(full, {"theta": np.zeros(5)})
        image, objects = cls.render(full, {"theta": np.zeros(3)}, objects=True)     # the options pass through
        assert image.shape == (3, 2, 2, 3) and objects.shape == (3, 2, 2)
        cls.render_bases(coarse, {"theta": np.zeros(4)})
        cls.render(full, {"theta": np.float32(0.5), "scale": np.ones(3)})      # one scene, not its scale's 3
        assert (clock.calls, clock.scenes) == (4, 13)
        assert clock.seconds["render"] >= 0.0 and clock.seconds["bases"] >= 0.0
        assert {size: scenes for size, (_, scenes) in clock.by_size.items()} == {(120, 160): 9, (60, 80): 4}
    assert mitsuba_renderer.MitsubaRenderer.render is render
    assert mitsuba_renderer.MitsubaRenderer.render_bases is render_bases


def test_the_posterior_time_probe_counts_each_event_by_its_own_time(tmp_path):
    """experiments/probe_posterior_time.py ``--profile``: an event's own time is its duration less what ran
    nested inside it on its thread (a while loop is not charged for the kernels it ran), threads apart."""
    import gzip
    import json

    probe = load_script("probe_posterior_time")
    events = [{"ph": "X", "name": "sweeps", "ts": 0, "dur": 100, "pid": 1, "tid": 1},
              {"ph": "X", "name": "fusion", "ts": 10, "dur": 30, "pid": 1, "tid": 1},
              {"ph": "X", "name": "fusion", "ts": 50, "dur": 20, "pid": 1, "tid": 1},
              {"ph": "X", "name": "callback", "ts": 55, "dur": 60, "pid": 1, "tid": 2},
              {"ph": "i", "name": "marker", "ts": 5, "pid": 1, "tid": 1}]
    path = tmp_path / "perfetto_trace.json.gz"
    with gzip.open(path, "wt") as f:
        json.dump({"traceEvents": events}, f)
    table = {name: (seconds * 1e6, calls) for name, seconds, calls in probe.own_times(path)}
    assert table == {"callback": (60, 1), "fusion": (50, 2), "sweeps": (50, 1)}


def test_the_delayed_acceptance_probe_counts_a_perfect_and_a_blind_screen():
    """experiments/probe_delayed_acceptance.py's rates: a screen that is the full likelihood accepts
    what the plain walk accepts and pays a full render only for those it passes; a blind screen
    passes everything and accepts no more than the plain walk."""
    rates = load_script("probe_delayed_acceptance").rates
    rng = np.random.default_rng(0)
    full, prior = rng.normal(-1.0, 2.0, 10_000), np.zeros(10_000)
    perfect = rates(full, full, prior, 1.0, 0.25)
    assert perfect["delayed"] == pytest.approx(perfect["plain"])
    assert perfect["screen"] == pytest.approx(perfect["plain"])
    assert perfect["gain"] == pytest.approx(1.0 / (0.25 + perfect["plain"]))
    blind = rates(full, np.zeros(10_000), prior, 1.0, 0.25)
    assert blind["screen"] == 1.0 and blind["delayed"] <= blind["plain"] + 1e-12 and blind["gain"] < 1.0


def test_the_sbc_bias_probe_finds_the_class_whose_ranks_lean():
    """experiments/probe_sbc_bias.py's per-class table: uniform ranks pass, ranks piled at the top of
    one class fail its KS test and show in its mean rank and its share outside all draws."""
    table = load_script("probe_sbc_bias").class_table
    rng = np.random.default_rng(1)
    classes = np.repeat([0, 1], 300)
    ranks = rng.integers(0, 100, (600, 2))
    ranks[classes == 1, 0] = rng.integers(70, 100, 300)
    fair, leaning = table(ranks, classes, 99)
    assert fair["count"] == leaning["count"] == 300
    assert fair["ks_p"].min() > 1e-3 and abs(fair["mean_rank"][0] - 49.5) < 6
    assert leaning["ks_p"][0] < 1e-6 and leaning["mean_rank"][0] > 80 and leaning["ks_p"][1] > 1e-3
    assert leaning["outside"][0] > fair["outside"][0]


def test_colour_centres_from_posteriors_leave_the_held_out_class_out():
    """experiments/select_colour_centres.py: a centre becomes the mean of the *other* classes' posterior
    chromaticities of its colour and kind (evaluate's rule, the class held out); a key only the held-out class
    holds keeps the fit's centre, and a colour the fit never saw its label's."""
    from types import SimpleNamespace

    from mitsuba_p3.fit.attributes import AttributeRules

    module = load_script("select_colour_centres")
    rules = AttributeRules(None, "rubber", ["red", "brown", "blue"],
                           np.array([[0.6, 0.2, 0.2], [0.45, 0.32, 0.23], [0.2, 0.2, 0.6]]),
                           colour_kinds=["rubber", "rubber", None])

    def posterior(chroma, n=5):     # k_a + k_d = 1: the median reflectance's chromaticity is the colour's
        samples = {"colour": np.tile(chroma, (n, 1)), "ambient": np.full((n, 1), 0.3),
                   "diffuse": np.full((n, 1), 0.7), "specular": np.full((n, 1), 0.2), "shininess": np.full((n, 1), 4.0)}
        return SimpleNamespace(program=SimpleNamespace(samples=samples))

    posteriors = {"large-red-rubber-cube": {0: posterior([0.5, 0.3, 0.2])},
                  "small-red-rubber-sphere": {0: posterior([0.7, 0.1, 0.2]), 1: posterior([0.7, 0.2, 0.1])},
                  "large-brown-rubber-cube": {0: posterior([0.5, 0.3, 0.2])}}
    labels = {name: SimpleNamespace(colour=name.split("-")[1], material="rubber") for name in posteriors}
    out = module.held_out_centres(rules, posteriors, labels, "large-brown-rubber-cube")
    np.testing.assert_allclose(out.colour_albedos[0], [0.633333, 0.2, 0.166667], atol=1e-6)   # all three red
    np.testing.assert_allclose(out.colour_albedos[1], [0.45, 0.32, 0.23])      # only the held-out class: the fit's
    np.testing.assert_allclose(out.colour_albedos[2], [0.2, 0.2, 0.6])         # a colour the fit never saw: its label
    out = module.held_out_centres(rules, posteriors, labels, "small-red-rubber-sphere")
    np.testing.assert_allclose(out.colour_albedos[0], [0.5, 0.3, 0.2])
    np.testing.assert_allclose(rules.colour_albedos[0], [0.6, 0.2, 0.2])       # the rules given are not changed


def test_shape_at_truth_margins_are_the_true_shape_less_the_best_wrong_one():
    """experiments/shape_at_truth.py --smc: a true shape behind the best wrong one has a negative margin, and the
    summary counts only the images it leads in."""
    probe = load_script("shape_at_truth")
    rows = [{"sphere": {"x": 10.0}, "cube": {"x": 4.0}, "cylinder": {"x": 7.0}},
            {"sphere": {"x": 1.0}, "cube": {"x": 3.0}, "cylinder": {"x": -2.0}}]
    margins = [probe.true_shape_margin(row, "sphere", "x") for row in rows]
    assert margins == [3.0, -2.0]
    assert probe.true_shape_margin(rows[1], "cube", "x") == 2.0
    assert probe.margin_summary(margins) == {"median": 0.5, "min": -2.0, "true_shape_ahead": [1, 2]}


def test_fit_starts_keep_the_default_seed_in_the_named_folder():
    """experiments/compare_fit_starts.py: the default start (777) is the folder named, every other seed a sibling
    ``NAME-sSEED``, so the default fit is read rather than refitted."""
    from pathlib import Path

    probe = load_script("compare_fit_starts")
    assert probe.start_folder(Path("data/models/studio-white"), 777) == Path("data/models/studio-white")
    assert probe.start_folder(Path("data/models/studio-white"), 2) == Path("data/models/studio-white-s2")


def test_train_scores_summarise_the_island_gaps_they_have():
    """experiments/score_train_attributes.py: median, p90 and the count over 10 nats of the finite island gaps
    (an MH posterior has none); no gaps, no figures."""
    probe = load_script("score_train_attributes")
    summary = probe.gap_summary([0.5, 1.0, float("nan"), 2.0, 30.0])
    assert summary["island_gap_median"] == 1.5 and summary["island_gap_over_10"] == 1
    assert 2.0 < summary["island_gap_p90"] < 30.0
    assert probe.gap_summary([float("nan")]) == {}


def test_the_rounds_replay_reads_each_round_from_the_runs_and_refuses_runs_out_of_order():
    """experiments/probe_rounds.py: a posterior's runs replayed round by round, as the sampler's rule made them. Round 1
    runs every hypothesis twice; the rule then keeps the two still in contention (the cube is 50 nats behind), round 2
    runs only those, and the replay's pooled evidence after each round is the log of the mean of the runs so far. Runs
    that are not a round of the contenders are refused, and the standard-error rule decides only once the runs agree."""
    probe = load_script("probe_rounds")
    log_prior = np.log(np.full(3, 1 / 3))
    index = np.array([0, 1, 2, 0, 1, 2, 0, 2, 0, 2])
    evidence = np.array([10.0, -40.0, 10.5, 12.0, -41.0, 9.0, 10.0, 10.0, 11.0, 10.5])
    rounds = probe.replay(index, evidence, log_prior, islands=2, threshold=0.99)
    assert [used for _, used, _ in rounds] == [6, 10]
    first, second = rounds[0][0], rounds[1][0]
    assert first[0] == pytest.approx(np.log(np.mean(np.exp([10.0, 12.0]))))
    assert second[2] == pytest.approx(np.log(np.mean(np.exp([10.5, 9.0, 10.0, 10.5]))))
    assert second[1] == first[1]                     # the cube ran no second round
    with pytest.raises(ValueError, match="not a round"):
        probe.replay(np.array([0, 1, 2, 0, 1, 2, 0, 1, 0, 1]), evidence, log_prior, islands=2, threshold=0.99)

    runs = [np.array([20.0, 20.1, 19.9, 20.0]), np.array([0.0, 0.1, -0.1, 0.0]), np.array([1.0, 1.0, 1.1, 0.9])]
    assert probe.standard_error_decided(log_prior, runs, 0.99)
    assert not probe.standard_error_decided(log_prior, [r[:1] for r in runs], 0.99)     # one run: no error known
    close = [np.array([5.0, 1.0, 1.2, 0.8]), np.array([4.0, 4.1, 3.9, 4.0]), np.array([0.0, 0.1, -0.1, 0.0])]
    assert not probe.standard_error_decided(log_prior, close, 0.99)


def test_run_streams_replay_spends_one_run_per_round_and_keeps_the_leaders_second():
    """experiments/probe_run_streams.py: one run per hypothesis and round stops after three runs on an image the first
    round decides, spends its most on both contenders of a close call (and drops the hypothesis 60 nats behind after its
    one run); "leader-twice" gives the decided leader its second run, the island gap's."""
    probe = load_script("probe_run_streams")
    log_prior = np.log(np.full(3, 1 / 3))
    decided = [np.array([10.0, 10.2, 10.1, 9.9]), np.full(4, -50.0), np.full(4, -40.0)]
    assert probe.replay_streams(decided, log_prior, 0.99, "one")[1:] == (3, False)
    assert probe.replay_streams(decided, log_prior, 0.99, "leader-twice")[1:] == (4, False)
    close = [np.array([10.0, 8.0, 9.0, 11.0]), np.full(4, -50.0), np.array([9.5, 10.5, 9.0, 9.0])]
    pooled, runs, short = probe.replay_streams(close, log_prior, 0.99, "one")
    assert (runs, short) == (9, False)
    assert pooled[0] == pytest.approx(np.log(np.mean(np.exp(close[0]))))
    assert probe.replay_streams([s[:2] for s in close], log_prior, 0.99, "one")[2]      # the cache held only two
    with pytest.raises(ValueError, match="unknown scheme"):
        probe.replay_streams(close, log_prior, 0.99, "two")


def test_each_distance_writes_its_own_tables_folder(tmp_path):
    """The default distance's tables go to the run folder; each other one to a folder named by what differs,
    in the order collect() parses them back."""
    from mitsuba_p3.concepts import DistanceConfig
    from mitsuba_p3.evaluate import tables_dir

    assert tables_dir(tmp_path, DistanceConfig()) == tmp_path
    assert tables_dir(tmp_path, DistanceConfig(tails=False)) == tmp_path / "gaussian-concepts"
    assert (tables_dir(tmp_path, DistanceConfig(direction="class||image", tails=False))
            == tmp_path / "kl-class-image-gaussian-concepts")
    assert tables_dir(tmp_path, DistanceConfig(spread_shots=0, tails=False)) == tmp_path / "spread0"  # no kernels to differ
    assert (tables_dir(tmp_path, DistanceConfig(properties=("colour", "class"), tails=False))
            == tmp_path / "distance-colour+class-gaussian-concepts")


def test_the_seed_swap_probe_scores_again_only_the_episodes_that_hold_the_swapped_image():
    """experiments/probe_seed_swaps.py: an image's posterior swapped in moves the cells, and scoring again only the
    episodes that hold it gives what scoring every episode gives."""
    from types import SimpleNamespace

    from mitsuba_p3.evaluate.config import EvaluationConfig
    from mitsuba_p3.evaluate.jobs import CachedPosterior

    probe = load_script("probe_seed_swaps")
    shots = {f"c{c}": [SimpleNamespace(index=3 * c + j) for j in range(3)] for c in range(6)}
    dataset = SimpleNamespace(classes=lambda split: sorted(shots), shots_of=lambda name: shots[name])
    rng = np.random.default_rng(2)

    def posterior(centre: float) -> CachedPosterior:
        return CachedPosterior(program(rng, centre, 0.05), np.zeros(2), 0.0, 0, 1.0, float("nan"), float("nan"))

    a = {3 * c + j: posterior(float(c)) for c in range(6) for j in range(3)}
    config = EvaluationConfig(episodes=30, distance=DistanceConfig(samples=100))
    settings = [(5, 1), (5, 2)]
    base = probe.episode_scores(dataset, a, None, settings, config)
    assert probe.cells(base).tolist() == [100.0, 100.0]
    swapped = {**a, 4: posterior(3.0)}                        # an image of class c1 read as class c3
    partial = probe.episode_scores(dataset, swapped, None, settings, config, only={4}, base=base)
    whole = probe.episode_scores(dataset, swapped, None, settings, config)
    assert all(np.array_equal(p, w) for p, w in zip(partial, whole))
    assert (probe.cells(whole) < 100.0).all()
