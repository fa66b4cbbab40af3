"""Reading and writing images as float32 (H, W, 3) arrays in [0, 1], row 0 at the top."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import MitsubaP3Error


class ImageError(MitsubaP3Error):
    """An image file is missing, unreadable or not an RGB picture."""


def read_png(path: str | Path) -> np.ndarray:
    """Read an 8- or 16-bit PNG/JPEG as float32 RGB in [0, 1].

    Greyscale is expanded to RGB; an alpha channel that is fully opaque is
    dropped, any other alpha is rejected (it would silently change colours).
    """
    from PIL import Image, UnidentifiedImageError

    path = Path(path)
    if not path.is_file():
        raise ImageError(f"{path}: no such image file")
    try:
        with Image.open(path) as im:
            im.load()
            mode = im.mode
            arr = np.asarray(im)
    except (UnidentifiedImageError, OSError) as exc:
        raise ImageError(f"{path}: cannot read image ({exc})") from None
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        data = arr.astype(np.float32) / 65535.0
    elif arr.dtype == np.uint8:
        data = arr.astype(np.float32) / 255.0
    elif arr.dtype == np.uint16:
        data = arr.astype(np.float32) / 65535.0
    elif arr.dtype == bool:
        data = arr.astype(np.float32)
    else:
        raise ImageError(f"{path}: unsupported image mode {mode!r}")
    if data.ndim == 2:
        data = np.repeat(data[:, :, None], 3, axis=2)
    elif data.shape[2] == 2:  # grey + alpha
        data = np.concatenate([np.repeat(data[:, :, :1], 3, axis=2), data[:, :, 1:]], axis=2)
    if data.shape[2] == 4:
        if not np.all(data[:, :, 3] >= 1.0 - 1e-6):
            raise ImageError(f"{path}: image has transparent pixels; flatten it onto a background first")
        data = data[:, :, :3]
    if data.shape[2] != 3:
        raise ImageError(f"{path}: expected an RGB image, got {data.shape[2]} channels")
    return np.ascontiguousarray(data, dtype=np.float32)


def to_uint8(image: np.ndarray) -> np.ndarray:
    """float [0, 1] -> uint8, rounding to nearest."""
    return (np.clip(np.asarray(image, dtype=np.float32), 0.0, 1.0) * 255.0 + 0.5).astype(np.uint8)


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a float (H, W, 3) image in [0, 1] as an 8-bit PNG (atomically)."""
    from PIL import Image

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageError(f"{path}: can only write (H, W, 3) images, got shape {image.shape}")
    tmp = path.with_name(path.name + ".tmp")
    Image.fromarray(to_uint8(image)).save(tmp, format="PNG")
    tmp.replace(path)
    return path
