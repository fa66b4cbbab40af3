"""The standard few-shot Conv-4 backbone, as pure JAX functions of a parameter pytree.

Four blocks of [3x3 conv, 64 filters, BatchNorm, ReLU, 2x2 max-pool] (Vinyals et
al. 2016; Snell et al. 2017; Finn et al. 2017). Functional parameters make MAML's
inner loop a plain ``jax.grad``. BatchNorm always normalises with the statistics
of the batch it is given (as the original MAML code does, at training and at
test time), so the model has no running averages to carry.
"""
from __future__ import annotations

import jax
import jax.numpy as jnp
import numpy as np

FILTERS = 64
BLOCKS = 4
EPSILON = 1e-5


def init_params(key, channels: int = 3, filters: int = FILTERS) -> list[dict]:
    """He-initialised convolutions, BatchNorm scale 1 and shift 0."""
    params = []
    for _ in range(BLOCKS):
        key, sub = jax.random.split(key)
        fan_in = 9 * channels
        params.append({"w": jax.random.normal(sub, (3, 3, channels, filters)) * np.sqrt(2.0 / fan_in),
                       "b": jnp.zeros(filters), "gamma": jnp.ones(filters), "beta": jnp.zeros(filters)})
        channels = filters
    return params


def block(p: dict, x):
    x = jax.lax.conv_general_dilated(x, p["w"], (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC")) + p["b"]
    mean = x.mean(axis=(0, 1, 2))
    var = x.var(axis=(0, 1, 2))
    x = (x - mean) * jax.lax.rsqrt(var + EPSILON) * p["gamma"] + p["beta"]
    return max_pool2(jax.nn.relu(x))


def max_pool2(x):
    """2x2 max-pool, stride 2, VALID (an odd last row or column is dropped).

    Written as a reshape and a max rather than ``lax.reduce_window``: the same values,
    but its gradient is a compare-and-select instead of XLA's ``select_and_scatter``,
    which is slow on CPU (``scripts/bench_baselines.py`` measures it). On ties a max's gradient is shared among the tied
    inputs instead of going to the first; after ReLU the only ties are at 0, where the
    ReLU passes no gradient, so the gradients agree too.
    """
    b, h, w, c = x.shape
    x = x[:, :h // 2 * 2, :w // 2 * 2].reshape(b, h // 2, 2, w // 2, 2, c)
    return x.max(axis=(2, 4))


def feature_map(params: list[dict], images):
    """(B, H, W, 3) images in [0, 1] -> (B, h, w, filters): the last block's map."""
    x = images - 0.5
    for p in params:
        x = block(p, x)
    return x


def embed(params: list[dict], images):
    """(B, H, W, 3) images in [0, 1] -> (B, features) embeddings (flattened last block)."""
    x = feature_map(params, images)
    return x.reshape(x.shape[0], -1)


def feature_size(resolution: int, filters: int = FILTERS) -> int:
    side = resolution
    for _ in range(BLOCKS):
        side //= 2
    return side * side * filters
