"""What an SMC run may take where it runs: particles per device, and memory before the first render.

On a GPU the JAX tracer's batched renders are cheap in width, so a run there takes more particles
(:data:`GPU_PARTICLES`); on the CPU, and for Mitsuba's callbacks anywhere, it keeps the default. The
widest step of a run (the first reweighting's oversampled draws, as material bases) is checked
against the memory there is before anything renders.
"""
from __future__ import annotations

# SMC particles per hypothesis and run where the JAX tracer renders on a GPU, chosen on train images under two
# seeds: two seeds' runs agree best at 512 (results/gpu/README.md)
GPU_PARTICLES = 512


def default_particles(renderer: str = "mitsuba", platform: str | None = None) -> int:
    """The SMC's particles per hypothesis for a renderer where this runs: :data:`GPU_PARTICLES` for the
    JAX tracer on a GPU, else :attr:`~mitsuba_p3.infer.smc.SMCConfig.particles` (Mitsuba's callbacks on
    a GPU are bound by launches and copies, not width)."""
    from .smc import SMCConfig

    from ..backend import jax_on_gpu

    if renderer != "jax":
        return SMCConfig.particles
    return GPU_PARTICLES if jax_on_gpu(platform) else SMCConfig.particles


def check_sampler_memory(config, hypotheses: int, pixels: int, limit: float | None = None) -> None:
    """Refuse, before any render, :class:`~mitsuba_p3.infer.smc.SMCConfig` settings whose widest step
    (the first reweighting: every hypothesis's ``islands`` x ``particles`` x ``oversample`` draws of
    ``pixels`` each, as material bases) would need more memory than ``limit`` bytes (default: the
    renderer's, :func:`~mitsuba_p3.render.contract.memory_limit`), with the largest particle count
    that fits."""
    from ..errors import InferenceError
    from ..render.contract import BYTES_PER_PIXEL, memory_limit

    limit = memory_limit() if limit is None else limit
    renders = hypotheses * config.islands * config.particles * config.oversample
    need = renders * pixels * BYTES_PER_PIXEL["bases"]
    if need > limit:
        fits = int(limit // (hypotheses * config.islands * config.oversample * pixels * BYTES_PER_PIXEL["bases"]))
        raise InferenceError(f"{config.particles:,} particles: the SMC's first step renders {renders:,} images of "
                             f"{pixels:,} pixels, about {need / 2 ** 30:,.1f} GB, over the limit of "
                             f"{limit / 2 ** 30:.1f} GB; use --particles {max(fits, 4)} or fewer (or set "
                             "MITSUBA_P3_MEMORY_GB)")
