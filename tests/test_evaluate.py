"""End-to-end evaluation: cached posteriors survive kill -9, episodes, tables, Dask."""
from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import asdict, replace

import numpy as np
import pytest

from mitsuba_p3.benchmarks.dataset import load_dataset
from mitsuba_p3.errors import EvaluationError
from mitsuba_p3.concepts import CONTINUOUS, DistanceConfig
from mitsuba_p3.evaluate import (EvaluationConfig, check_run, compute_posteriors, evaluate, posterior_path)
from mitsuba_p3.evaluate.run import spread_shots
from mitsuba_p3.fit.model import fit_model
from mitsuba_p3.fit.scene_opt import SceneOptConfig
from mitsuba_p3.infer.mcmc import SamplerConfig

RES = (30, 40)
TINY = SamplerConfig(chains=4, steps=30, burn_in=10, tune_rounds=2, tune_steps=20, block=10, init_candidates=32)
SAMPLER_FLAGS = ["--chains", "4", "--steps", "30", "--burn-in", "10", "--tune-rounds", "2", "--tune-steps", "20"]
# a small SMC for the CLI's runs (the default's posterior takes 40-120 s even at 30x40): what they test is the run
# folder, not the sampler
SMC_FLAGS = ["--particles", "4", "--set", "smc.mcmc_steps=1", "--set", "smc.final_steps=1", "--set", "smc.islands=1",
             "--set", "smc.rounds=1"]


@pytest.fixture(scope="module")
def bench(tmp_path_factory):
    from mitsuba_p3.benchmarks.generate import generate

    root = tmp_path_factory.mktemp("evaluate")
    generate("fsclvr", root / "data", seed=5, size="small", resolution=RES, spp=8)
    # no material refinement at this tiny size (see tests/test_infer.py's fixture)
    fit_model(root / "data", root / "model", scene_config=SceneOptConfig(resolution=RES, pattern_size=16, epochs=1,
                                                                         material_passes=1, global_passes=2,
                                                                         refine_materials=False))
    return root


@pytest.mark.slow
def test_evaluate_resumes_after_kill_and_writes_tables(bench, tmp_path):
    run = tmp_path / "run"
    command = [sys.executable, "-m", "mitsuba_p3.cli", "evaluate", str(bench / "data"), "--model",
               str(bench / "model"), "--out", str(run), "--likelihoods", "p3", "--episodes", "20", *SAMPLER_FLAGS,
               *SMC_FLAGS]
    first = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    folder = run / "posteriors" / "p3"
    deadline = time.time() + 600
    while time.time() < deadline and len(list(folder.glob("*.npz"))) < 2:
        time.sleep(0.5)
    os.killpg(first.pid, signal.SIGKILL)
    first.wait()
    finished = {p: p.stat().st_mtime_ns for p in folder.glob("*.npz")}
    assert len(finished) >= 2
    dataset = load_dataset(bench / "data")
    images = len(dataset.split("test")) + len(spread_shots(dataset, DistanceConfig.spread_shots))
    assert len(finished) < images, "killed too late to test resuming"

    result = subprocess.run(command, capture_output=True, text=True, timeout=1200)
    assert result.returncode == 0, result.stderr
    assert {p: p.stat().st_mtime_ns for p in finished} == finished      # not recomputed
    assert len(list(folder.glob("*.npz"))) == images        # test images, and train images for the spread
    spread = json.loads((run / f"spread-p3-{DistanceConfig.spread_shots}.json").read_text())
    assert spread["classes"] == 5 and spread["images"] == 15 and 0 <= spread["class_error"] <= 1
    assert set(spread["tails"]) == set(CONTINUOUS)                  # the concept's kernels' fitted tails
    assert not list(folder.glob("*.tmp*"))
    results = json.loads((run / "results.json").read_text())["results"]["p3"]
    assert json.loads((run / "material-rule-p3.json").read_text())["format"] == "mitsuba-p3-material-rule"
    accuracy = results["accuracy"]["5-way 1-shot"]
    assert 0.0 <= accuracy["mean"] <= 1.0 and accuracy["episodes"] == 20 and 0 <= accuracy["ece"] <= 1
    assert "5-way 5-shot" not in results["accuracy"]      # 3 shots per class cannot make it
    assert 0 < results["adi"]["mean"] < 0.2 and len(results["adi_per_class"]) == 5
    for name in ("accuracy.md", "accuracy.csv", "adi.md", "adi.csv", "reliability.png", "predictions.csv"):
        assert (run / name).is_file(), name
    assert "P3" in (run / "accuracy.md").read_text()

    # another distance: the same posteriors, its own tables, the paper distance's left alone
    paper_results = (run / "results.json").read_bytes()
    every = {p: p.stat().st_mtime_ns for p in folder.glob("*.npz")}
    fewer = subprocess.run(command + ["--distance", "colour+class"], capture_output=True, text=True, timeout=600)
    assert fewer.returncode == 0, fewer.stderr
    assert {p: p.stat().st_mtime_ns for p in every} == every
    assert (run / "results.json").read_bytes() == paper_results
    chosen = json.loads((run / "distance-colour+class" / "results.json").read_text())
    assert chosen["distance"] == ["colour", "class"] and chosen["results"]["p3"]["accuracy"]["5-way 1-shot"]["episodes"] == 20
    assert (run / "distance-colour+class" / "accuracy.md").is_file()
    paper = subprocess.run(command + ["--spread-shots", "0"], capture_output=True, text=True, timeout=600)
    assert paper.returncode == 0, paper.stderr
    assert (run / "results.json").read_bytes() == paper_results
    assert json.loads((run / "spread0" / "results.json").read_text())["results"]["p3"]["accuracy"]
    gaussian = subprocess.run(command + ["--gaussian-concepts"], capture_output=True, text=True, timeout=600)
    assert gaussian.returncode == 0, gaussian.stderr
    assert (run / "results.json").read_bytes() == paper_results
    assert json.loads((run / "gaussian-concepts" / "results.json").read_text())["concept_tails"] is False
    assert json.loads((run / f"spread-p3-{DistanceConfig.spread_shots}-gaussian.json").read_text())["tails"] == {}
    bad = subprocess.run(command + ["--distance", "colour+hue"], capture_output=True, text=True, timeout=300)
    assert bad.returncode != 0 and "hue" in bad.stderr

    # a setting of the sampler this run used (SMC under the default fitted noise: chains would not count)
    other = subprocess.run(command + ["--particles", "12"], capture_output=True, text=True, timeout=300)
    assert other.returncode == 2 and "other settings" in other.stderr


@pytest.mark.slow
def test_workers_die_with_a_killed_evaluate(bench, tmp_path):
    """SIGKILL of the main process alone (not its group): its joblib workers exit within seconds."""
    command = [sys.executable, "-m", "mitsuba_p3.cli", "evaluate", str(bench / "data"), "--model",
               str(bench / "model"), "--out", str(tmp_path / "run"), "--likelihoods", "p3", "--jobs", "2",
               *SAMPLER_FLAGS]
    main = subprocess.Popen(command, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, start_new_session=True)
    group = os.getsid(main.pid)

    def others():
        alive = []
        for entry in os.listdir("/proc"):
            try:
                if entry.isdigit() and int(entry) != main.pid and os.getsid(int(entry)) == group:
                    alive.append(int(entry))
            except (ProcessLookupError, PermissionError):
                pass
        return alive

    folder = tmp_path / "run" / "posteriors" / "p3"
    deadline = time.time() + 300
    while time.time() < deadline and not list(folder.glob("*.npz")):      # the workers are computing
        time.sleep(0.5)
    assert len(others()) >= 2
    os.kill(main.pid, signal.SIGKILL)
    main.wait()
    deadline = time.time() + 60
    while time.time() < deadline and others():
        time.sleep(0.5)
    left = others()
    for pid in left:
        os.kill(pid, signal.SIGKILL)
    assert not left, f"workers still running after their parent was killed: {left}"


@pytest.mark.slow
def test_posteriors_on_a_dask_cluster(bench, tmp_path):
    from dask.distributed import LocalCluster

    dataset = load_dataset(bench / "data")
    shots = [s.index for s in dataset.split("test")[:2]]
    with LocalCluster(n_workers=1, threads_per_worker=1, processes=True, dashboard_address=None) as cluster:
        config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, dask=cluster.scheduler_address)
        compute_posteriors(dataset, bench / "model", tmp_path, config, shots=shots)
    for index in shots:
        with np.load(posterior_path(tmp_path, "p3", index)) as f:
            assert f["sample_colour"].shape[1] == 3 and f["sample_class"].ndim == 1


@pytest.mark.slow
def test_parallel_workers_share_the_cores(bench, tmp_path):
    """With --jobs 2 every worker renders with its share of the cores, not all of them."""
    from mitsuba_p3.evaluate import worker_threads

    assert worker_threads(1) is None
    dataset = load_dataset(bench / "data")
    shots = [s.index for s in dataset.split("test")[:2]]
    compute_posteriors(dataset, bench / "model", tmp_path, EvaluationConfig(likelihoods=("p3",), sampler=TINY, jobs=2),
                       shots=shots)
    for index in shots:
        with np.load(posterior_path(tmp_path, "p3", index)) as f:
            assert int(f["render_threads"]) == worker_threads(2)


def test_a_jax_tracer_worker_needs_no_mitsuba_and_shares_the_gpu(monkeypatch):
    """A worker of an evaluation under the JAX tracer sets XLA's threads and leaves Dr.Jit alone (such
    a run works where Mitsuba is not installed, as on a lent GPU machine); every worker takes device
    memory as it needs it, so several can share one GPU. Under Mitsuba the worker needs Dr.Jit, and says so."""
    import sys

    from mitsuba_p3.evaluate import jobs

    # a copy of the environment without the two variables, so that what the worker sets stays in this test
    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items()
                                        if k not in ("XLA_FLAGS", "XLA_PYTHON_CLIENT_PREALLOCATE")})
    monkeypatch.setitem(sys.modules, "drjit", None)        # import drjit now raises ImportError
    jobs._limit_threads(1, "jax")
    assert jobs._render_threads("jax") == 0
    assert os.environ["XLA_FLAGS"] == jobs.SINGLE_THREAD_XLA_FLAGS
    assert os.environ["XLA_PYTHON_CLIENT_PREALLOCATE"] == "false"
    from mitsuba_p3.errors import BackendError

    # the backend's error where Mitsuba was not imported yet, else Dr.Jit's own import error
    with pytest.raises((BackendError, ImportError), match="Mitsuba|drjit"):
        jobs._limit_threads(1, "mitsuba")


_HELD = []


def _hold_and_name(megabytes: int, fail: bool = False) -> int:
    """A worker's job: keep ``megabytes`` more memory alive, then name its process (or fail). Each takes
    over a second, as loky checks a worker's memory at most once a second."""
    time.sleep(1.1)
    if fail:
        raise ValueError("this job fails")
    _HELD.append(np.ones(megabytes << 17))              # 8-byte floats: megabytes MB, touched
    return os.getpid()


def test_workers_live_for_the_whole_run():
    """A worker whose memory grows by more than 300 MB after its first job (as a posterior worker's does
    when JAX compiles its later programs) keeps its process: loky's executor replaced it, and the new
    process compiled everything again. An error in a job reaches the caller."""
    from mitsuba_p3.evaluate.jobs import in_workers

    pids = list(in_workers(_hold_and_name, [(8,), (200,), (200,), (200,)], workers=1))
    assert len(set(pids)) == 1 and pids[0] != os.getpid()
    with pytest.raises(ValueError, match="this job fails"):
        list(in_workers(_hold_and_name, [(1,), (1, True), (1,)], workers=2))


def test_run_folder_refuses_other_settings(bench, tmp_path):
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, episodes=2)
    dataset = load_dataset(bench / "data")
    check_run(tmp_path, dataset, bench / "model", config)
    check_run(tmp_path, dataset, bench / "model", config)                   # same settings: fine
    # nothing cached yet (a run that died at its start): the corrected command takes the folder over
    other = EvaluationConfig(likelihoods=("p3",), sampler=TINY, sigma=0.1)
    check_run(tmp_path, dataset, bench / "data", other)
    assert json.loads((tmp_path / "run.json").read_text())["sigma"] == 0.1
    check_run(tmp_path, dataset, bench / "model", config)
    compute_posteriors(dataset, bench / "model", tmp_path, config, shots=[dataset.split("test")[0].index])
    with pytest.raises(EvaluationError, match="another model"):             # cached posteriors of another model
        check_run(tmp_path, dataset, bench / "data", config)
    with pytest.raises(EvaluationError, match="sigma"):                     # another likelihood sigma
        check_run(tmp_path, dataset, bench / "model", EvaluationConfig(likelihoods=("p3",), sampler=TINY, sigma=0.1))
    changed = EvaluationConfig(likelihoods=("p3",), sampler=SamplerConfig(**{**asdict(TINY), "steps": 31}))
    with pytest.raises(EvaluationError, match="other settings"):
        evaluate(bench / "data", bench / "model", tmp_path, changed)


def test_a_run_folder_of_the_fields_earlier_form_is_refused(bench, tmp_path):
    """Posteriors cached under the shading fields' earlier form (the power on the whole marginal; its run.json
    names no ``fields_power_on``) are not resumed under today's: the folder is refused; one of today's resumes."""
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, noise="fields")
    dataset = load_dataset(bench / "data")
    check_run(tmp_path, dataset, bench / "model", config)
    assert json.loads((tmp_path / "run.json").read_text())["fields_power_on"] == "pixels"
    (tmp_path / "posteriors" / "p3").mkdir(parents=True)
    (tmp_path / "posteriors" / "p3" / "0.npz").write_bytes(b"")             # a cached posterior, as far as run.json cares
    check_run(tmp_path, dataset, bench / "model", config)
    record = json.loads((tmp_path / "run.json").read_text())
    del record["fields_power_on"]
    (tmp_path / "run.json").write_text(json.dumps(record))
    with pytest.raises(EvaluationError, match="fields_power_on"):
        check_run(tmp_path, dataset, bench / "model", config)


def test_a_run_folder_of_the_scaled_noises_first_form_is_refused(bench, tmp_path):
    """Posteriors cached when the image's own scale was tempered in from the prior (their run.json names no
    ``scale_form``) are not resumed under today's bridged form; the fixed scale's folders do not carry the key."""
    dataset = load_dataset(bench / "data")
    assert "scale_form" not in EvaluationConfig(likelihoods=("p3",), sampler=TINY, noise="fields").cache_key()
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, noise="scaled")
    check_run(tmp_path, dataset, bench / "model", config)
    (tmp_path / "posteriors" / "p3").mkdir(parents=True)
    (tmp_path / "posteriors" / "p3" / "0.npz").write_bytes(b"")
    check_run(tmp_path, dataset, bench / "model", config)                  # today's form resumes
    record = json.loads((tmp_path / "run.json").read_text())
    assert record["scale_form"] == "bridged"
    del record["scale_form"]
    (tmp_path / "run.json").write_text(json.dumps(record))
    with pytest.raises(EvaluationError, match="scale_form"):
        check_run(tmp_path, dataset, bench / "model", config)


def test_a_run_with_tuple_settings_resumes(bench, tmp_path):
    """Settings that are tuples (the SMC's window) read back from run.json as lists: a rerun with the
    same settings over cached posteriors resumes rather than being refused as 'other settings'."""
    from mitsuba_p3.infer.smc import SMCConfig

    config = EvaluationConfig(likelihoods=("p3",), noise="fitted", sampler=SMCConfig(particles=4, window=(48, 64)))
    dataset = load_dataset(bench / "data")
    check_run(tmp_path, dataset, bench / "model", config)
    (tmp_path / "posteriors" / "p3").mkdir(parents=True)
    (tmp_path / "posteriors" / "p3" / "0.npz").write_bytes(b"")             # a cached posterior, as far as run.json cares
    check_run(tmp_path, dataset, bench / "model", config)
    with pytest.raises(EvaluationError, match="other settings"):
        check_run(tmp_path, dataset, bench / "model", replace(config, sampler=SMCConfig(particles=4, window=(56, 72))))
    # a record written before a sampler setting existed (persistent sampling here) was at its default: it resumes
    record = json.loads((tmp_path / "run.json").read_text())
    del record["sampler"]["persistent"], record["sampler"]["waste_free"]
    (tmp_path / "run.json").write_text(json.dumps(record))
    check_run(tmp_path, dataset, bench / "model", config)
    with pytest.raises(EvaluationError, match="other settings"):
        check_run(tmp_path, dataset, bench / "model", replace(config, sampler=SMCConfig(particles=4, window=(48, 64),
                                                                                        persistent=True, wide_steps=0)))
    # ... but one written before the wide start existed had none, whatever today's default: it does not resume
    for key in ("wide", "wide_steps", "coarse", "symmetry"):
        del record["sampler"][key]
    (tmp_path / "run.json").write_text(json.dumps(record))
    with pytest.raises(EvaluationError, match="other settings"):
        check_run(tmp_path, dataset, bench / "model", config)
    check_run(tmp_path, dataset, bench / "model", replace(config, sampler=replace(config.sampler, wide_steps=0,
                                                                                  coarse=1, wide=1, symmetry="free")))


def test_the_bridge_setting_guards_only_np3_posteriors(bench, tmp_path):
    """The SMC's bridge decides how NP3's posteriors are made and nothing of P3's: a folder made before
    the setting existed (no 'bridge' in its record: NP3 tempered from the prior) still serves P3 runs;
    an NP3 run with the bridge on is refused while it holds NP3 posteriors, and takes the folder over
    once it holds none."""
    from mitsuba_p3.infer.smc import SMCConfig

    dataset = load_dataset(bench / "data")
    old = EvaluationConfig(likelihoods=("p3", "np3"), noise="fitted", sampler=SMCConfig(particles=4, bridge=False))
    check_run(tmp_path, dataset, bench / "model", old)
    record = json.loads((tmp_path / "run.json").read_text())
    del record["sampler"]["bridge"]
    (tmp_path / "run.json").write_text(json.dumps(record))
    for likelihood in ("p3", "np3"):
        (tmp_path / "posteriors" / likelihood).mkdir(parents=True)
        (tmp_path / "posteriors" / likelihood / "00000.npz").write_bytes(b"")
    check_run(tmp_path, dataset, bench / "model", old)                       # read as bridge off: the same run
    new = replace(old, sampler=SMCConfig(particles=4))
    check_run(tmp_path, dataset, bench / "model", replace(new, likelihoods=("p3",)))    # P3 alone: unaffected
    with pytest.raises(EvaluationError, match="bridge off"):
        check_run(tmp_path, dataset, bench / "model", new)
    with pytest.raises(EvaluationError, match="other settings"):              # anything else still refuses
        check_run(tmp_path, dataset, bench / "model", replace(old, sampler=SMCConfig(particles=5, bridge=False)))
    (tmp_path / "posteriors" / "np3" / "00000.npz").unlink()
    check_run(tmp_path, dataset, bench / "model", new)
    assert json.loads((tmp_path / "run.json").read_text())["sampler"]["bridge"] is True


def test_a_bridged_np3_job_starts_from_p3s_cached_particles(bench, tmp_path):
    """P3's job caches its SMC particles; NP3's job of the same image starts from them, and the result
    is the posterior NP3 reaches when it runs P3 itself (the sampler is seeded)."""
    from mitsuba_p3.evaluate.jobs import posterior_job
    from mitsuba_p3.infer.smc import SMCConfig

    dataset = load_dataset(bench / "data")
    shot = dataset.split("test")[0].index
    # no wide start and one round: where NP3 starts from is tested, not P3's start (minutes of compilation)
    config = EvaluationConfig(likelihoods=("p3", "np3"), noise="fitted",
                              sampler=SMCConfig(particles=4, mcmc_steps=1, final_steps=1, draws=40, wide_steps=0,
                                                rounds=1))
    compute_posteriors(dataset, bench / "model", tmp_path / "both", config, shots=[shot])
    with np.load(posterior_path(tmp_path / "both", "p3", shot)) as f:
        assert f["particles_position"].shape[1:] == (4, 15) and np.all(np.isfinite(f["particles_log_evidence"]))
    alone = tmp_path / "alone" / "posteriors" / "np3" / f"{shot:05d}.npz"
    alone.parent.mkdir(parents=True)
    posterior_job(str(bench / "data"), str(bench / "model"), shot, "np3", config, str(alone))
    with np.load(alone) as a, np.load(posterior_path(tmp_path / "both", "np3", shot)) as b:
        np.testing.assert_array_equal(a["sample_shift"], b["sample_shift"])
        np.testing.assert_array_equal(a["log_evidence"], b["log_evidence"])
        assert "particles_position" not in b.files                        # only P3's runs are started from


def test_a_model_or_data_set_changed_in_place_is_noticed(bench, tmp_path):
    """A model fitted again into the same folder (or labels rewritten) no longer matches the cached
    posteriors: the run refuses it rather than reuse them; and fit refuses to mix a second data set into
    a model folder."""
    import shutil

    from mitsuba_p3.errors import FitError

    model, data = tmp_path / "model", tmp_path / "data"
    shutil.copytree(bench / "model", model)
    shutil.copytree(bench / "data", data)
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, episodes=2)
    run = tmp_path / "run"
    check_run(run, load_dataset(data), model, config)
    (run / "posteriors" / "p3").mkdir(parents=True)
    (run / "posteriors" / "p3" / "00000.npz").write_bytes(b"")        # a cached posterior
    check_run(run, load_dataset(data), model, config)
    info = json.loads((model / "model.json").read_text())
    (model / "model.json").write_text(json.dumps({**info, "refitted": True}))
    with pytest.raises(EvaluationError, match="another model .*changed since"):
        check_run(run, load_dataset(data), model, config)
    with pytest.raises(FitError, match="holds a model fitted to"):
        fit_model(data, bench / "model")                            # the copy is another data set


def test_sigma_reaches_the_cached_posteriors(bench, tmp_path):
    """A smaller colour sigma sharpens the likelihood, so the same image's colour posterior narrows. (With
    4 short chains the spread at sigma 0.05 bottoms out at the chains' own dispersion, 0.03-0.05 against
    0.08-0.10 at sigma 1 from machine to machine: the bound leaves room for that, and a sigma that did not
    reach the posteriors, ratio about 1, still fails.)"""
    dataset = load_dataset(bench / "data")
    shot = dataset.split("test")[0].index
    spreads = {}
    for sigma in (1.0, 0.05):
        config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, sigma=sigma)
        compute_posteriors(dataset, bench / "model", tmp_path / f"s{sigma}", config, shots=[shot])
        with np.load(posterior_path(tmp_path / f"s{sigma}", "p3", shot)) as f:
            spreads[sigma] = f["sample_colour"].std(axis=0).mean()
    assert spreads[0.05] < 0.75 * spreads[1.0]


def test_cli_refuses_a_bad_sigma(bench, tmp_path):
    result = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "evaluate", str(bench / "data"), "--model",
                             str(bench / "model"), "--out", str(tmp_path), "--sigma", "0"],
                            capture_output=True, text=True, timeout=300)
    assert result.returncode != 0 and "sigma" in result.stderr


def test_refusals_come_before_any_work(bench, tmp_path):
    """A data set without train classes (like ood) needs the spread of its model's own run; a Dask
    scheduler must answer; classes must fill a few-shot setting: all refused before a posterior or
    run.json exists."""
    import shutil

    data = tmp_path / "data"
    shutil.copytree(bench / "data", data)
    labels = json.loads((data / "labels.json").read_text())
    tests_only = {**labels, "images": [r for r in labels["images"] if r["split"] == "test"]}
    (data / "labels.json").write_text(json.dumps(tests_only))
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY)
    with pytest.raises(EvaluationError, match="--spread-from"):
        evaluate(data, bench / "model", tmp_path / "run", config)
    # a spread written before concept kernels had tails would silently score with Gaussian ones
    old = tmp_path / "old-run"
    old.mkdir()
    (old / f"spread-p3-{DistanceConfig.spread_shots}.json").write_text(json.dumps(
        {"covariance": {}, "class_error": 0.1, "images": 15, "classes": 5}))
    with pytest.raises(EvaluationError, match="before concept spreads had fitted tails"):
        evaluate(data, bench / "model", tmp_path / "run", config, spread_from=old)
    with pytest.raises(EvaluationError, match="no Dask scheduler answers"):
        evaluate(bench / "data", bench / "model", tmp_path / "run",
                 EvaluationConfig(likelihoods=("p3",), sampler=TINY, dask="tcp://127.0.0.1:1"))
    one_shot = {**labels, "images": [r for r in labels["images"] if r["shot"] == 0]}
    (data / "labels.json").write_text(json.dumps(one_shot))
    with pytest.raises(EvaluationError, match="fill none of the few-shot settings"):
        evaluate(data, bench / "model", tmp_path / "run", config)
    assert not (tmp_path / "run").exists()


def test_a_damaged_cached_posterior_is_kept_aside_and_sampled_again(bench, tmp_path):
    dataset = load_dataset(bench / "data")
    shot = dataset.split("test")[0].index
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY)
    path = posterior_path(tmp_path, "p3", shot)
    path.parent.mkdir(parents=True)
    path.write_bytes(b"")                                          # zero bytes
    compute_posteriors(dataset, bench / "model", tmp_path, config, shots=[shot])
    with np.load(path) as f:
        assert f["sample_colour"].shape[1] == 3
    assert path.with_suffix(".corrupt").read_bytes() == b""


def test_a_second_run_into_a_busy_folder_is_refused(bench, tmp_path):
    """While one evaluation holds its run folder, another into the same folder stops at once; the
    lock goes with its holder."""
    from mitsuba_p3.errors import MitsubaP3Error
    from mitsuba_p3.files import folder_lock

    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY, episodes=2)
    holder = subprocess.Popen([sys.executable, "-c", "import sys, time; from mitsuba_p3.files import folder_lock\n"
                               f"with folder_lock({str(tmp_path / 'run')!r}, 'test'):\n"
                               "    print('held', flush=True); time.sleep(60)"], stdout=subprocess.PIPE, text=True)
    assert holder.stdout.readline().strip() == "held"
    with pytest.raises(MitsubaP3Error, match=f"in use by another run \\(pid {holder.pid}\\)"):
        evaluate(bench / "data", bench / "model", tmp_path / "run", config)
    assert not list((tmp_path / "run").glob("posteriors/*/*.npz"))
    holder.kill()
    holder.wait()
    with folder_lock(tmp_path / "run", "test"):             # released with its dead holder
        pass


def test_reproduce_writes_one_posterior_figure_per_benchmark_once(bench, tmp_path):
    """``reproduce``'s posterior figure: a seeded test image's posterior, sampled with the run's settings
    and written as ``infer`` writes it; a resumed reproduction copies it and does not sample again."""
    from mitsuba_p3.reproduce import example_shot, posterior_figure

    config = EvaluationConfig(likelihoods=("p3",), noise="paper", sampler=TINY)
    figure = posterior_figure(bench / "data", bench / "model", tmp_path / "run", config,
                              tmp_path / "figures" / "posterior-fsclvr.png")
    example = tmp_path / "run" / "example"
    estimate = json.loads((example / "estimate.json").read_text())
    assert figure.stat().st_size > 5000 and (example / "posterior.nc").is_file()
    assert estimate["attributes"]["shape"] in ("sphere", "cube", "cylinder")
    shot = example_shot(load_dataset(bench / "data"))
    assert shot.split == "test" and example_shot(load_dataset(bench / "data")).index == shot.index
    made = (example / "posterior.nc").stat().st_mtime_ns
    posterior_figure(bench / "data", bench / "model", tmp_path / "run", config, figure)
    assert (example / "posterior.nc").stat().st_mtime_ns == made


@pytest.mark.slow
def test_reproduce_logs_its_time_and_resumes_without_sampling_again(bench, tmp_path, monkeypatch):
    """``reproduce`` from a data folder (benchmark + fitted model): the paper's tables, one timing record per
    benchmark whose parts add up to the call's wall time, and a second call that samples nothing again."""
    import mitsuba_p3.benchmarks.generate as generate_module
    from mitsuba_p3.reproduce import ReproduceConfig, reproduce

    # the fixture's benchmark is a small one of its own seed: nothing to generate
    monkeypatch.setattr(generate_module, "generate", lambda *args, **kwargs: None)

    data = tmp_path / "data"
    (data / "models").mkdir(parents=True)
    (data / "fsclvr").symlink_to(bench / "data")
    (data / "models" / "fsclvr").symlink_to(bench / "model")
    config = ReproduceConfig(benchmarks=("fsclvr",), evaluation=EvaluationConfig(
        likelihoods=("p3",), noise="paper", sampler=TINY, episodes=5))
    start = time.perf_counter()
    minutes = reproduce(data, tmp_path / "out", config)
    wall = (time.perf_counter() - start) / 60
    log = json.loads((tmp_path / "out" / "timing.json").read_text())
    assert len(log) == 1 and set(minutes) == {"fsclvr"}
    parts = log[0]["generate_and_fit_minutes"] + log[0]["minutes"] + log[0]["figure_and_tables_minutes"]
    assert 0 < parts <= wall + 0.01 and parts > 0.9 * wall
    from mitsuba_p3.reproduce import posterior_figure_name

    # the paper's noise is not the headline's: its figure is named after its run
    for name in ("accuracy.md", "accuracy.csv", "adi.md", f"figures/{posterior_figure_name('fsclvr', None)}"):
        assert (tmp_path / "out" / name).is_file(), name
    posteriors = {p: p.stat().st_mtime_ns for p in (tmp_path / "out" / "runs").rglob("*.npz")}
    assert posteriors
    reproduce(data, tmp_path / "out", config)
    assert {p: p.stat().st_mtime_ns for p in posteriors} == posteriors
    assert len(json.loads((tmp_path / "out" / "timing.json").read_text())) == 2


def test_a_posterior_of_a_replaced_image_is_set_aside(tmp_path):
    """A cache answers for the image bytes it was sampled from: a replaced image's posterior is
    moved aside (NAME.stale) and sampled again; a cache from before digests is trusted."""
    from mitsuba_p3.evaluate.jobs import _cached

    path = tmp_path / "7.npz"
    np.savez(path, sample_class=np.zeros(3, np.int8), seconds=np.float64(1.0), image_digest=np.array("aaa"))
    assert _cached(path, "aaa") and path.exists()
    assert not _cached(path, "bbb") and not path.exists() and path.with_suffix(".stale").exists()
    np.savez(path, sample_class=np.zeros(3, np.int8), seconds=np.float64(1.0))
    assert _cached(path, "bbb")


@pytest.mark.slow
def test_evaluate_samples_again_for_an_image_replaced_in_place(bench, tmp_path):
    import shutil

    data = tmp_path / "data"
    shutil.copytree(bench / "data", data)
    dataset = load_dataset(data)
    shot = dataset.split("test")[0]
    config = EvaluationConfig(likelihoods=("p3",), sampler=TINY)
    compute_posteriors(dataset, bench / "model", tmp_path / "run", config, shots=[shot.index])
    path = posterior_path(tmp_path / "run", "p3", shot.index)
    with np.load(path) as f:
        first = str(f["image_digest"])
    from PIL import Image

    Image.new("RGB", Image.open(shot.file).size).save(shot.file)      # an all-black image in its place
    compute_posteriors(load_dataset(data), bench / "model", tmp_path / "run", config, shots=[shot.index])
    assert path.with_suffix(".stale").exists()
    with np.load(path) as f:
        assert str(f["image_digest"]) != first


def test_reliability_bins_carry_the_wilson_interval_and_the_figure_is_written(tmp_path):
    """The reliability diagram's error bars: the Wilson score interval, which stays inside [0, 1] for a bin of three
    queries all wrong (0 to 0.56) and of twenty all right, and is the textbook's for five of ten."""
    from mitsuba_p3.plots import reliability_diagram, wilson_interval

    low, high = wilson_interval(np.array([0.0, 0.5, 1.0]), np.array([3, 10, 20]))
    assert low == pytest.approx([0.0, 0.2366, 0.8389], abs=1e-4)
    assert high == pytest.approx([0.5615, 0.7634, 1.0], abs=1e-4)
    bins = [[None, None, 0], [0.45, 0.0, 3], [0.55, 0.5, 4], [0.99, 0.98, 480], [1.0, 1.0, 20]]
    results = {"p3": {"accuracy": {"5-way 1-shot": {"reliability": bins, "ece": 0.02}}}}
    path = reliability_diagram(tmp_path / "reliability.png", results, ["5-way 1-shot", "10-way 5-shot"])
    assert path.is_file() and path.stat().st_size > 0
