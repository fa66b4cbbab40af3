"""Reading and writing images as float32 (H, W, 3) arrays in [0, 1], row 0 at the top."""
from __future__ import annotations

from pathlib import Path

import numpy as np

from .errors import ImageError
from .files import atomic_path

INFERENCE_RESOLUTION = (120, 160)   # (H, W): the size inference and fitting work at
ASPECT_TOLERANCE = 0.01



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
            im.load()                                   # the first frame of an animation
            # colours, not the file's encoding: palette entries (PNG mode P, GIF), CMYK or YCbCr JPEGs
            if im.mode in ("P", "PA"):
                im = im.convert("RGBA")
            elif im.mode in ("CMYK", "YCbCr", "LAB", "HSV"):
                im = im.convert("RGB")
            elif im.mode == "1":
                im = im.convert("L")
            mode = im.mode
            arr = np.asarray(im)
    except (UnidentifiedImageError, OSError) as exc:
        raise ImageError(f"{path}: cannot read image ({exc})") from None
    if mode in ("I;16", "I;16B", "I;16L", "I"):
        # mode I is 32-bit: read as 16-bit (how PIL opens some 16-bit files) only where its values fit
        if mode == "I" and arr.size and (arr.min() < 0 or arr.max() > 65535):
            raise ImageError(f"{path}: 32-bit integer values {int(arr.min())}..{int(arr.max())} are not an 8- or "
                             "16-bit image's; save it as an 8- or 16-bit PNG")
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


# what an output image's suffix asks for (Pillow format names)
IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG"}


def check_image_output(path: str | Path) -> Path:
    """Refuse, before any work, an output image path that could not be written as asked: a folder
    (or a name ending in a slash), a parent that is a file, a suffix other than .png/.jpg/.jpeg."""
    text = str(path)
    path = Path(path)
    if text.endswith(("/", "\\")) or path.is_dir():
        raise ImageError(f"{text} is a folder; give an image file name such as {path / 'image.png'}")
    suffix = path.suffix.lower()
    if suffix not in IMAGE_FORMATS:
        raise ImageError(f"{path}: cannot write {suffix or 'a file without a suffix'}; "
                         f"name it {path.with_suffix('.png').name} (or .jpg)")
    for parent in path.parents:
        if parent.exists():
            if not parent.is_dir():
                raise ImageError(f"{path}: {parent} is a file, not a folder")
            break
    from .files import refuse_inside_protected

    refuse_inside_protected(path, "writing an image")
    return path


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write a float (H, W, 3) image in [0, 1] as its suffix says: 8-bit PNG or JPEG (quality 95)."""
    path = check_image_output(path)
    return _save(path, image, IMAGE_FORMATS[path.suffix.lower()])


def write_png(path: str | Path, image: np.ndarray) -> Path:
    """Write a float (H, W, 3) image in [0, 1] as an 8-bit PNG (atomically), whatever the name."""
    return _save(Path(path), image, "PNG")


def _save(path: Path, image: np.ndarray, format: str) -> Path:
    from PIL import Image

    image = np.asarray(image)
    if image.ndim != 3 or image.shape[2] != 3:
        raise ImageError(f"{path}: can only write (H, W, 3) images, got shape {image.shape}")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as temporary:
        Image.fromarray(to_uint8(image)).save(temporary, format=format, **({"quality": 95} if format == "JPEG" else {}))
    return path


def load_image(path: Path, resolution: tuple[int, int]) -> np.ndarray:
    """Read an image and resize it (area averaging) to ``resolution`` = (H, W), same aspect."""
    return resize_image(read_png(path), resolution, str(path))


def resize_image(image: np.ndarray, resolution: tuple[int, int], source: str = "image") -> np.ndarray:
    """Resize (H, W, 3) float [0, 1] to ``resolution`` by area averaging; the aspect must match."""
    from PIL import Image

    height, width = resolution
    h, w = image.shape[:2]
    if abs((w / h) / (width / height) - 1.0) > ASPECT_TOLERANCE:
        raise ImageError(f"{source}: aspect {w}x{h} (W x H) differs from the inference resolution "
                         f"{width}x{height}; crop it to {width}:{height} first")
    if (h, w) == (height, width):
        return np.asarray(image, np.float32)
    channels = [np.asarray(Image.fromarray(image[..., c], mode="F").resize((width, height), Image.BOX))
                for c in range(3)]
    return np.clip(np.stack(channels, axis=-1), 0.0, 1.0).astype(np.float32)


def load_observation(path: str | Path, resolution: tuple[int, int] = INFERENCE_RESOLUTION) -> np.ndarray:
    """An observed image as float32 (H, W, 3) in [0, 1] at ``resolution``.

    PNG/JPEG (8 or 16 bit, grey or RGB, opaque RGBA) are converted; ``.npy``
    float arrays in [0, 1] are accepted. Transparent pixels, NaN or infinite
    values, values outside [0, 1] and another aspect ratio are rejected with
    the reason.
    """
    path = Path(path)
    if path.suffix.lower() != ".npy":
        return load_image(path, resolution)
    try:
        array = np.load(path, allow_pickle=False)
    except (OSError, ValueError) as exc:
        raise ImageError(f"{path}: cannot read array ({exc})") from None
    return observation_array(array, str(path), resolution)


def observation_array(array, source: str = "image", resolution: tuple[int, int] = INFERENCE_RESOLUTION) -> np.ndarray:
    """An in-memory image (H, W), (H, W, 3) or opaque (H, W, 4) of real numbers in [0, 1] as float32
    (H, W, 3) at ``resolution``: the checks a ``.npy`` file gets (shape, dtype, finite, range, opaque,
    aspect), each refused in one line naming ``source``."""
    array = np.asarray(array)
    if array.dtype.kind not in "fiub" or array.dtype.kind == "b" or array.size == 0:
        raise ImageError(f"{source}: expected an image of real numbers in [0, 1], got a {array.dtype} array of "
                         f"shape {array.shape}")
    array = np.asarray(array, np.float32)
    if array.ndim == 2:
        array = np.repeat(array[..., None], 3, axis=-1)
    if array.ndim != 3 or array.shape[-1] not in (3, 4) or min(array.shape[:2]) < 8:
        raise ImageError(f"{source}: expected an (H, W, 3) image array of at least 8x8, got shape {array.shape}")
    if not np.all(np.isfinite(array)):
        raise ImageError(f"{source}: the image has NaN or infinite values")
    if array.min() < 0.0 or array.max() > 1.0:
        raise ImageError(f"{source}: values must lie in [0, 1] (found {array.min():.3g}..{array.max():.3g}); "
                         "divide 8-bit data by 255")
    if array.shape[-1] == 4:
        if not np.all(array[..., 3] >= 1.0 - 1e-6):
            raise ImageError(f"{source}: the image has transparent pixels; flatten it onto a background first")
        array = array[..., :3]
    return resize_image(array, resolution, source)
