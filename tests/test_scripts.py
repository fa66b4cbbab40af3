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
    """A script of ``scripts/`` imported as a module (its ``main`` is not run)."""
    import importlib.util
    import sys
    from pathlib import Path

    root = Path(__file__).resolve().parents[1]
    path = root / "scripts" / f"{name}.py"
    if str(path.parent) not in sys.path:       # a script may import its neighbours
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




def test_only_the_headline_run_writes_the_benchmarks_posterior_figure():
    """A reproduction under the paper's likelihood (or another sigma) names its posterior figure after
    its run, so it does not overwrite the headline run's ``posterior-V.png``."""
    from mitsuba_p3.infer.likelihood import DEFAULT_NOISE

    assert tables.posterior_figure_name("room", DEFAULT_NOISE) == "posterior-room.png"
    assert tables.posterior_figure_name("room", "fitted") == "posterior-room-fitted.png"
    assert tables.posterior_figure_name("room", None) == "posterior-room-paper.png"
    assert tables.posterior_figure_name("dark", 0.35) == "posterior-dark-sigma0.35.png"
    assert tables.posterior_figure_name("ood", "robust") == "posterior-ood-robust.png"


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


