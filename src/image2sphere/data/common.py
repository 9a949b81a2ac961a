"""Pieces shared by the datasets: image loading and normalisation, seeded shuffling, collation.

Conventions
-----------
* Images reach the network as float32 ``(3, H, W)``, normalised with the ImageNet mean and
  standard deviation (what torchvision's ResNet weights expect).
* Randomness in data loading is a function of ``(seed, epoch, index)`` only, never of a global
  random state, so a run resumed from a checkpoint sees the same batches as an uninterrupted one.
"""

from __future__ import annotations

import hashlib
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch.utils.data import Sampler

__all__ = [
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "EpochShuffleSampler",
    "load_image",
    "normalize_images",
    "stable_seed",
]

IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts, identical across processes and Python versions."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def load_image(path: str | Path, image_size: int | None = None) -> torch.Tensor:
    """An RGB image file as uint8 ``(H, W, 3)``, resized (bilinear, antialiased) to a square ``image_size``.

    Raises ``FileNotFoundError`` / ``ValueError`` naming the file when it is missing or unreadable.
    """
    path = Path(path)
    try:
        with Image.open(path) as im:
            im = im.convert("RGB")
            if image_size is not None and im.size != (image_size, image_size):
                im = im.resize((image_size, image_size), Image.Resampling.BILINEAR, reducing_gap=None)
            array = np.asarray(im, dtype=np.uint8).copy()
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {path}") from None
    except (UnidentifiedImageError, OSError, SyntaxError) as e:
        raise ValueError(f"cannot decode image {path} ({e}); the file is corrupt: re-download or re-render it") from e
    return torch.from_numpy(array)


def normalize_images(images: torch.Tensor) -> torch.Tensor:
    """uint8 ``(..., H, W, 3)`` -> float32 ``(..., 3, H, W)`` with ImageNet normalisation."""
    x = images.movedim(-1, -3).to(torch.float32) / 255.0
    mean = torch.tensor(IMAGENET_MEAN, dtype=x.dtype)[:, None, None]
    std = torch.tensor(IMAGENET_STD, dtype=x.dtype)[:, None, None]
    return (x - mean) / std


class EpochShuffleSampler(Sampler[int]):
    """A random permutation of ``range(n)`` that depends only on ``(seed, epoch)``.

    Lightning calls :meth:`set_epoch` before every training epoch; the dataset (if given) is told
    the epoch too, so its own per-item randomness can follow the same rule.
    """

    def __init__(self, n: int, seed: int, dataset: object | None = None):
        self.n = int(n)
        self.seed = int(seed)
        self.epoch = 0
        self.dataset = dataset

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        if self.dataset is not None and hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)

    def __iter__(self) -> Iterator[int]:
        g = torch.Generator().manual_seed(stable_seed("shuffle", self.seed, self.epoch))
        return iter(torch.randperm(self.n, generator=g).tolist())

    def __len__(self) -> int:
        return self.n
