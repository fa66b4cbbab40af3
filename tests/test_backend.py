"""libLLVM discovery: a usable library is found, and unusable ones fail with the fix."""
from __future__ import annotations

import os
import subprocess
import sys

import pytest

from mitsuba_p3 import backend
from mitsuba_p3.errors import BackendError


@pytest.mark.parametrize("name, version", [
    ("libLLVM-19.so", 19), ("libLLVM.so.19.1", 19), ("libLLVM-15.so.1", 15), ("libLLVM-14.0.6.so.1", 14),
    ("libLLVM.so", None), ("libc.so.6", None),
])
def test_version_from_file_name(name, version):
    assert backend.llvm_version_of(f"/usr/lib/{name}") == version


def test_finds_a_usable_llvm_here(monkeypatch):
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    path, version = backend.find_llvm()
    assert os.path.isfile(path) and version >= backend.MIN_LLVM_VERSION


def test_only_broken_versions_is_a_clear_error(monkeypatch, tmp_path):
    (tmp_path / "libLLVM-15.so").write_bytes(b"")
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(backend, "_SEARCH_GLOBS", (str(tmp_path / "libLLVM*.so*"),))
    with pytest.raises(BackendError, match="found only: .*libLLVM-15.so.*libllvm19"):
        backend.find_llvm()


@pytest.mark.parametrize("name, message", [("libLLVM-15.so", "LLVM 15"), ("missing.so", "does not exist")])
def test_bad_explicit_path(monkeypatch, tmp_path, name, message):
    if name != "missing.so":
        (tmp_path / name).write_bytes(b"")
    monkeypatch.setenv("DRJIT_LIBLLVM_PATH", str(tmp_path / name))
    with pytest.raises(BackendError, match=message):
        backend.find_llvm()


def test_cli_reports_a_broken_llvm_in_one_line(tmp_path):
    """No abort: a known-broken libLLVM is refused before Dr.Jit ever loads it."""
    fake = tmp_path / "libLLVM-15.so"
    fake.write_bytes(b"")
    env = {**os.environ, "DRJIT_LIBLLVM_PATH": str(fake)}
    done = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "doctor"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 2
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("error:") and "libllvm19" in lines[0]


def _has_cuda() -> bool:
    import drjit as dr

    backend.mitsuba()
    return dr.has_backend(dr.JitBackend.CUDA)


def test_variant_follows_the_device(monkeypatch):
    monkeypatch.delenv(backend.VARIANT_ENV, raising=False)
    variant, why = backend.choose_variant()
    assert variant == ("cuda_ad_rgb" if _has_cuda() else "llvm_ad_rgb") and why
    assert backend.mitsuba().variant() in backend.VARIANTS


def test_a_forced_variant_is_checked(monkeypatch):
    monkeypatch.setenv(backend.VARIANT_ENV, "scalar_rgb")
    with pytest.raises(BackendError, match="llvm_ad_rgb, cuda_ad_rgb"):
        backend.choose_variant()
    monkeypatch.setenv(backend.VARIANT_ENV, "llvm_ad_rgb")
    assert backend.choose_variant() == ("llvm_ad_rgb", f"forced by {backend.VARIANT_ENV}")
    if not _has_cuda():
        monkeypatch.setenv(backend.VARIANT_ENV, "cuda_ad_rgb")
        with pytest.raises(BackendError, match="no CUDA device"):
            backend.choose_variant()


def test_cli_variant_option_and_doctor(tmp_path):
    """`--variant` reaches the backend before Mitsuba loads; doctor says which variant and why, the
    XLA flags the process runs with, and the choices that follow the device (forced here by their variables)."""
    env = {k: v for k, v in os.environ.items() if k != backend.VARIANT_ENV}
    env.update(MITSUBA_P3_SMC_STEP="device", MITSUBA_P3_JAX_BATCHING="vmap")
    done = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "--variant", "llvm_ad_rgb", "doctor"], env=env,
                          capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    import json

    report = json.loads(done.stdout)
    assert report["variant"] == "llvm_ad_rgb" and "forced" in report["variant_why"]
    assert report["cpu_cores"] >= 1 and "jax_backend" in report
    assert report["smc_step"] == "device" and report["jax_batching"] == "vmap"
    import mitsuba_p3

    assert report["xla_flags"] == mitsuba_p3._xla_flags(env.get("XLA_FLAGS", ""), mitsuba_p3._jaxlib_version())
    bad = subprocess.run([sys.executable, "-m", "mitsuba_p3.cli", "--variant", "scalar_rgb", "doctor"], env=env,
                         capture_output=True, text=True, timeout=120)
    assert bad.returncode == 2 and "--variant must be one of" in bad.stderr


def test_jax_batching_follows_the_device(monkeypatch):
    from mitsuba_p3.render.jax_tracer import BATCHING_ENV, batching_for
    from mitsuba_p3.errors import SceneError

    monkeypatch.delenv(BATCHING_ENV, raising=False)
    assert batching_for("cpu") == "map" and batching_for("gpu") == "vmap"
    monkeypatch.setenv(BATCHING_ENV, "vmap")
    assert batching_for("cpu") == "vmap"
    monkeypatch.setenv(BATCHING_ENV, "pmap")
    with pytest.raises(SceneError, match="map, vmap"):
        batching_for()


def test_a_gpu_machine_without_libllvm_runs_the_cuda_variant(monkeypatch):
    """No usable libLLVM: the CUDA variant needs none, so a GPU (or a forced cuda_ad_rgb) goes on without
    it; without a GPU, or with llvm_ad_rgb forced, the missing-LLVM error stands."""
    def no_llvm():
        raise BackendError("no usable libLLVM")

    monkeypatch.setattr(backend, "find_llvm", no_llvm)
    monkeypatch.delenv(backend.VARIANT_ENV, raising=False)
    monkeypatch.delenv("DRJIT_LIBLLVM_PATH", raising=False)
    monkeypatch.setattr(backend, "_cuda_available", lambda: True)
    assert backend.llvm_path() is None
    monkeypatch.setenv(backend.VARIANT_ENV, "llvm_ad_rgb")
    with pytest.raises(BackendError, match="libLLVM"):
        backend.llvm_path()
    monkeypatch.delenv(backend.VARIANT_ENV)
    monkeypatch.setattr(backend, "_cuda_available", lambda: False)
    with pytest.raises(BackendError, match="libLLVM"):
        backend.llvm_path()
    monkeypatch.setenv(backend.VARIANT_ENV, "cuda_ad_rgb")
    assert backend.llvm_path() is None


@pytest.mark.parametrize("setting, expected", [(None, "{home}/.cache/mitsuba-p3/jax"), ("off", "None"),
                                               ("{home}/elsewhere", "{home}/elsewhere")])
def test_jax_compiles_once_per_machine_into_a_cache_one_can_move_or_turn_off(tmp_path, setting, expected):
    """Importing the package points JAX's persistent compilation cache at ~/.cache/mitsuba-p3/jax (so a
    second command does not compile the sampler again), MITSUBA_P3_JAX_CACHE moves it or turns it off,
    and a cache the user gave JAX is kept."""
    env = {k: v for k, v in os.environ.items()
           if k not in ("MITSUBA_P3_JAX_CACHE", "JAX_COMPILATION_CACHE_DIR", "XDG_CACHE_HOME")}
    env["HOME"] = str(tmp_path)
    if setting is not None:
        env["MITSUBA_P3_JAX_CACHE"] = setting.format(home=tmp_path)
    show = "import mitsuba_p3, os; print(os.environ.get('JAX_COMPILATION_CACHE_DIR'))"
    out = subprocess.run([sys.executable, "-c", show], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == expected.format(home=tmp_path)
    env["JAX_COMPILATION_CACHE_DIR"] = str(tmp_path / "mine")
    out = subprocess.run([sys.executable, "-c", show], env=env, capture_output=True, text=True, check=True)
    assert out.stdout.strip() == str(tmp_path / "mine")


def test_xla_flags_leave_ynnpack_out_only_where_jaxlib_knows_the_flag(monkeypatch):
    """The package keeps XLA's CPU backend from handing fusions to YNNPACK where jaxlib has the flag
    (0.8.1 on: XLA stops a process on a flag it does not know), keeps every flag the user set, and
    leaves flags that name the YNNPACK fusions, or MITSUBA_P3_YNNPACK=on, as they are."""
    import mitsuba_p3

    monkeypatch.delenv("MITSUBA_P3_YNNPACK", raising=False)
    off = mitsuba_p3.NO_YNNPACK
    assert mitsuba_p3._xla_flags("", "0.10.2") == off
    assert mitsuba_p3._xla_flags("--xla_dump_to=d", "0.8.1") == f"--xla_dump_to=d {off}"
    for old in ("0.8.0", "0.4.30", None, "dev"):
        assert mitsuba_p3._xla_flags("--xla_dump_to=d", old) == "--xla_dump_to=d"
    mine = "--xla_cpu_experimental_ynn_fusion_type=individual_dot"
    assert mitsuba_p3._xla_flags(mine, "0.10.2") == mine
    monkeypatch.setenv("MITSUBA_P3_YNNPACK", "on")
    assert mitsuba_p3._xla_flags("", "0.10.2") == ""


def test_an_evaluation_worker_adds_its_single_thread_to_the_packages_xla_flags(monkeypatch):
    """A worker's single-threaded XLA goes beside the flags already set (the package's own among them);
    thread flags a user set are kept."""
    from mitsuba_p3.evaluate import jobs

    monkeypatch.setattr(os, "environ", {k: v for k, v in os.environ.items() if k != "XLA_FLAGS"})
    os.environ["XLA_FLAGS"] = "--xla_dump_to=d"
    jobs._limit_threads(1, "jax")
    assert os.environ["XLA_FLAGS"] == f"--xla_dump_to=d {jobs.SINGLE_THREAD_XLA_FLAGS}"
    os.environ["XLA_FLAGS"] = "--xla_cpu_multi_thread_eigen=true"
    jobs._limit_threads(1, "jax")
    assert os.environ["XLA_FLAGS"] == "--xla_cpu_multi_thread_eigen=true"


def test_jax_runs_under_the_packages_xla_flags():
    """A process that imports the package first starts XLA with its flags (XLA stops a process on a flag
    its jaxlib does not know, so this fails if a jaxlib drops the flag the package adds)."""
    import mitsuba_p3

    show = ("import os, mitsuba_p3, jax.numpy as jnp; "
            "print(float(jnp.einsum('pij,pik->pjk', jnp.ones((8, 3, 3)), jnp.ones((8, 3, 3))).sum())); "
            "print(os.environ.get('XLA_FLAGS', ''))")
    env = {k: v for k, v in os.environ.items() if k not in ("XLA_FLAGS", "MITSUBA_P3_YNNPACK")}
    out = subprocess.run([sys.executable, "-c", show], env={**env, "JAX_PLATFORMS": "cpu"},
                         capture_output=True, text=True)
    assert out.returncode == 0, out.stderr[-2000:]
    value, flags = out.stdout.splitlines()
    assert float(value) == 8 * 27
    assert flags == mitsuba_p3._xla_flags("", mitsuba_p3._jaxlib_version())
