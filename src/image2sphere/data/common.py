"""What every reader of the datasets and prediction share: the errors of reading a dataset, the rules
that decode an image file into 8-bit RGB, the ImageNet normalisation, and the seed of data randomness.

Conventions
-----------
* Images reach the network as float32 ``(3, H, W)``, normalised with the ImageNet mean and
  standard deviation (what torchvision's ResNet weights expect): :func:`normalize_images`.
* Image files of any mode are decoded by one set of rules (:func:`decode_image`), for the datasets
  and for prediction alike.
* Randomness in data loading is a function of ``(seed, epoch, index)`` only, through
  :func:`stable_seed` (see :mod:`image2sphere.data.loading`).
* A corrupt image inside a dataset raises :class:`CorruptImageError` naming the file (or LMDB key),
  or, with ``on_corrupt="skip"``, is logged (:func:`skip_corrupt`), dropped from its batch by
  :func:`~image2sphere.data.loading.collate_skipping_corrupt` and counted in the batch's ``skipped`` entry.
* A dataset that is not where the configuration says raises :class:`DatasetNotFoundError`
  (:func:`missing_dataset_error`).
"""

from __future__ import annotations

import hashlib
import io
import logging
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError

from image2sphere.checks import ConfigError, InputNotFoundError

__all__ = [
    "CORRUPT_POLICIES",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "CorruptImageError",
    "DatasetNotFoundError",
    "check_corrupt_policy",
    "decode_image",
    "image_to_uint8",
    "load_image",
    "missing_dataset_error",
    "normalize_images",
    "skip_corrupt",
    "stable_seed",
]

log = logging.getLogger(__name__)

CORRUPT_POLICIES = ("fail", "skip")


class CorruptImageError(ConfigError):
    """An image file (or LMDB record) that cannot be decoded; ``source`` names it."""

    def __init__(self, source: str, reason: str):
        self.source = source
        super().__init__(f"cannot decode image {source} ({reason}); the file is corrupt or truncated: re-download it")


class DatasetNotFoundError(InputNotFoundError):
    """A dataset is not where the configuration says (see :func:`missing_dataset_error`)."""


def missing_dataset_error(
    name: str, looked_at: Path, expected: str, get_from: str, key: str, docs: str | None = None
) -> DatasetNotFoundError:
    """The error for a dataset that is missing or incomplete: where we looked, what should be there,
    where to get it, which config key points at it and (``docs``) where the layout is described."""
    see = f" (the layout is described in {docs})" if docs else ""
    return DatasetNotFoundError(
        f"{name} not found at {looked_at}: expected {expected}. Get it from {get_from} and unpack it there, "
        f"or point {key} at your copy{see}"
    )


def check_corrupt_policy(value: str, key: str) -> str:
    if value not in CORRUPT_POLICIES:
        raise ConfigError(f"{key} must be one of {CORRUPT_POLICIES}, got {value!r}")
    return value


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts, identical across processes and Python versions."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


class _UnreadablePixels(ValueError):
    """Pixels that decode but cannot be read as an 8-bit image (e.g. a float image outside [0, 1])."""


_HIGH_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")
_ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")
_transparency_reported = False


def _gray_to_uint8(image: Image.Image, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A 16-bit, 32-bit integer or float grayscale image as 8-bit gray ``(H, W)``, and an alpha
    ``(H, W)`` when a ``transparency`` value marks pixels as transparent (else ``None``).

    16-bit samples (``I;16*``, and ``I``, which is how Pillow gives 16-bit PNG and TIFF samples) are
    divided by 257 (65535 -> 255); float (``F``) samples are intensities in ``[0, 1]``.
    """
    x = np.asarray(image)
    if image.mode == "F":
        x = x.astype(np.float64)
        if x.size and not (np.isfinite(x).all() and x.min() >= 0.0 and x.max() <= 1.0):
            low, high = (float(np.nanmin(x)), float(np.nanmax(x))) if np.isfinite(x).any() else (np.nan, np.nan)
            raise _UnreadablePixels(
                f"image {name} is a float image with values in [{low:g}, {high:g}] (or not finite); float images are "
                "read as intensities in [0, 1]: convert it to 8 or 16 bits, or scale it to [0, 1]"
            )
        gray = np.rint(x * 255.0)
    else:
        x = x.astype(np.int64)
        if x.size and (x.min() < 0 or x.max() > 65535):
            raise _UnreadablePixels(
                f"image {name} is a 32-bit integer image with values in [{x.min()}, {x.max()}]; integer images "
                "are read as 16-bit samples (0..65535): convert it to 8 or 16 bits"
            )
        gray = (x + 128) // 257  # round(x / 257)
    key = image.info.get("transparency")
    alpha = np.where(x == key, 0, 255).astype(np.uint8) if isinstance(key, (int, float)) else None
    return gray.astype(np.uint8), alpha


def _to_rgb(image: Image.Image, name: str) -> Image.Image:
    """``image`` as 8-bit RGB by the rules of :func:`decode_image` (loads every pixel)."""
    global _transparency_reported
    alpha = None
    if image.mode in _HIGH_DEPTH_MODES:
        gray, alpha = _gray_to_uint8(image, name)
        rgb = np.repeat(gray[..., None], 3, axis=-1)
    elif image.mode in _ALPHA_MODES or "transparency" in image.info:
        rgba = np.asarray(image.convert("RGBA"))
        rgb, alpha = rgba[..., :3], rgba[..., 3]
    elif image.mode == "RGB":
        return image.copy()  # a copy: the caller may close the file behind ``image``
    else:
        return image.convert("RGB")
    if alpha is not None and (alpha < 255).any():
        # composite onto black: out = rgb * alpha / 255, rounded
        rgb = ((rgb.astype(np.uint32) * alpha[..., None].astype(np.uint32) + 127) // 255).astype(np.uint8)
        if not _transparency_reported:
            _transparency_reported = True
            log.warning(
                "image %s has transparent pixels: composited onto black, the background of the rendered "
                "training images (reported once; later images are composited the same way)",
                name,
            )
    return Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8))


def decode_image(source: str | Path | bytes, name: str | None = None) -> Image.Image:
    """A fully decoded 8-bit RGB :class:`PIL.Image.Image` from a file path or encoded bytes.

    Conversion rules (shared by datasets and prediction, see :func:`image_to_uint8`):

    * grayscale and palette images become three equal channels;
    * 16-bit samples (modes ``I;16*``, and ``I``, Pillow's mode for 16-bit PNG and TIFF) are scaled to
      8 bits (divided by 257); ``I`` values outside ``0..65535`` are refused; float (``F``) samples
      are intensities in ``[0, 1]`` (anything else is refused);
    * transparency (an alpha channel: ``RGBA``, ``LA``, ``PA``; or a ``transparency`` colour, e.g. of
      palette images) is composited onto a **black** background, ``rgb * alpha / 255``: the
      background of the rendered training images (:mod:`image2sphere.data.render`). A warning is
      logged the first time an image with transparent pixels is met.

    Raises ``FileNotFoundError`` for a missing file, :class:`CorruptImageError` naming ``name``
    (default: the path) for anything that does not decode completely, truncated files included, and
    ``ValueError`` naming it for pixel values the rules above refuse.
    """
    name = name or (f"({len(source)} bytes in memory)" if isinstance(source, bytes) else str(source))
    try:
        with Image.open(io.BytesIO(source) if isinstance(source, bytes) else Path(source)) as im:
            im.load()  # every pixel, so truncation is detected here
            return _to_rgb(im, name)
    except FileNotFoundError:
        raise InputNotFoundError(f"image file not found: {name}") from None
    except _UnreadablePixels as e:
        raise ConfigError(str(e)) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise CorruptImageError(name, str(e)) from e


def load_image(source: str | Path | bytes, image_size: int | None = None, name: str | None = None) -> torch.Tensor:
    """An image (file path or encoded bytes) as uint8 RGB ``(H, W, 3)``, resized (bilinear,
    antialiased) to a square ``image_size`` when given. Conversion and errors as :func:`decode_image`.
    """
    return image_to_uint8(decode_image(source, name), image_size)


def image_to_uint8(image: Image.Image, image_size: int | None = None, name: str | None = None) -> torch.Tensor:
    """A PIL image as uint8 RGB ``(H, W, 3)``, resized (bilinear, antialiased) to a square ``image_size``.

    Any mode is converted by the rules of :func:`decode_image` (16-bit and float scaling,
    transparency composited onto black); ``name`` names the image in messages.
    """
    if image.mode != "RGB" or "transparency" in image.info:
        try:
            image = _to_rgb(image, name or "(in memory)")
        except _UnreadablePixels as e:
            raise ConfigError(str(e)) from None
    if image_size is not None and image.size != (image_size, image_size):
        image = image.resize((image_size, image_size), Image.Resampling.BILINEAR, reducing_gap=None)
    return torch.from_numpy(np.asarray(image, dtype=np.uint8).copy())


def skip_corrupt(error: CorruptImageError, policy: str, warned: set[str]) -> None:
    """Apply ``dataset.on_corrupt`` to a corrupt image: re-raise on ``"fail"``; on ``"skip"`` log it
    (once per image; ``warned`` remembers which) and return, the caller's item being ``None``."""
    if policy == "fail":
        raise error
    if error.source not in warned:
        warned.add(error.source)
        log.warning("skipping corrupt image %s (dataset.on_corrupt=skip)", error.source)


def normalize_images(images: torch.Tensor) -> torch.Tensor:
    """uint8 ``(..., H, W, 3)`` -> float32 ``(..., 3, H, W)`` with ImageNet normalisation."""
    x = images.movedim(-1, -3).to(torch.float32) / 255.0
    mean = torch.tensor(IMAGENET_MEAN, dtype=x.dtype)[:, None, None]
    std = torch.tensor(IMAGENET_STD, dtype=x.dtype)[:, None, None]
    return (x - mean) / std
