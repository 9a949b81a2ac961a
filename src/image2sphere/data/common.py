"""Pieces shared by the datasets: image loading and normalisation, seeded shuffling, collation,
corrupt-image handling, missing-dataset messages and the report of the ``verify`` commands.

Conventions
-----------
* Images reach the network as float32 ``(3, H, W)``, normalised with the ImageNet mean and
  standard deviation (what torchvision's ResNet weights expect).
* Randomness in data loading is a function of ``(seed, epoch, index)`` only, never of a global
  random state, so a run resumed from a checkpoint sees the same batches as an uninterrupted one.
* A corrupt image inside a dataset raises :class:`CorruptImageError` naming the file (or LMDB key),
  or, with ``on_corrupt="skip"``, is logged, dropped from its batch by :func:`collate_skipping_corrupt`
  and counted in the batch's ``skipped`` entry.
"""

from __future__ import annotations

import hashlib
import io
import logging
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch.utils.data import DataLoader, Sampler, default_collate

__all__ = [
    "CORRUPT_POLICIES",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "CorruptImageError",
    "DatasetNotFoundError",
    "EpochShuffleSampler",
    "PoseDataModule",
    "VerifyReport",
    "check_corrupt_policy",
    "collate_skipping_corrupt",
    "decode_image",
    "image_to_uint8",
    "load_image",
    "missing_dataset_error",
    "single_label_item",
    "skip_corrupt",
    "normalize_images",
    "stable_seed",
]

log = logging.getLogger(__name__)

CORRUPT_POLICIES = ("fail", "skip")


class CorruptImageError(ValueError):
    """An image file (or LMDB record) that cannot be decoded; ``source`` names it."""

    def __init__(self, source: str, reason: str):
        self.source = source
        super().__init__(f"cannot decode image {source} ({reason}); the file is corrupt or truncated: re-download it")


class DatasetNotFoundError(FileNotFoundError):
    """A dataset is not where the configuration says (see :func:`missing_dataset_error`)."""


def missing_dataset_error(name: str, looked_at: Path, expected: str, get_from: str, key: str) -> DatasetNotFoundError:
    """The error for a dataset that is missing or incomplete: where we looked, what should be there,
    where to get it and which config key points at it."""
    return DatasetNotFoundError(
        f"{name} not found at {looked_at}: expected {expected}. Get it from {get_from} and unpack it there, "
        f"or point {key} at your copy"
    )


def check_corrupt_policy(value: str, key: str) -> str:
    if value not in CORRUPT_POLICIES:
        raise ValueError(f"{key} must be one of {CORRUPT_POLICIES}, got {value!r}")
    return value


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts, identical across processes and Python versions."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


def decode_image(source: str | Path | bytes, name: str | None = None) -> Image.Image:
    """A fully decoded RGB :class:`PIL.Image.Image` from a file path or encoded bytes (grayscale and
    palette images are converted to three equal channels).

    Raises ``FileNotFoundError`` for a missing file and :class:`CorruptImageError` naming ``name``
    (default: the path) for anything that does not decode completely, truncated files included.
    """
    name = name or str(source)
    try:
        with Image.open(io.BytesIO(source) if isinstance(source, bytes) else Path(source)) as im:
            return im.convert("RGB")  # convert() loads every pixel, so truncation is detected here
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {name}") from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise CorruptImageError(name, str(e)) from e


def load_image(source: str | Path | bytes, image_size: int | None = None, name: str | None = None) -> torch.Tensor:
    """An image (file path or encoded bytes) as uint8 RGB ``(H, W, 3)``, resized (bilinear,
    antialiased) to a square ``image_size`` when given. Errors as :func:`decode_image`.
    """
    return image_to_uint8(decode_image(source, name), image_size)


def image_to_uint8(image: Image.Image, image_size: int | None = None) -> torch.Tensor:
    """A PIL image as uint8 RGB ``(H, W, 3)``, resized (bilinear, antialiased) to a square ``image_size``."""
    if image.mode != "RGB":
        image = image.convert("RGB")
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


def single_label_item(
    image: torch.Tensor, class_index: int, index: int, rotation: np.ndarray, return_all: bool
) -> dict[str, torch.Tensor]:
    """A dataset item with one rotation label: ``image`` uint8 ``(H, W, 3)`` normalised to ``(3, H, W)``,
    ``class_index``, ``index`` and ``rotation (3, 3)``, or for evaluation (``return_all``) the
    one-element set ``rotations (1, 3, 3)`` with ``mask (1,)``, the format of multi-label sets."""
    item = {
        "image": normalize_images(image),
        "class_index": torch.tensor(int(class_index), dtype=torch.int64),
        "index": torch.tensor(int(index), dtype=torch.int64),
    }
    rotation = torch.as_tensor(np.asarray(rotation, dtype=np.float32))
    if return_all:
        item["rotations"] = rotation[None]
        item["mask"] = torch.ones(1, dtype=torch.bool)
    else:
        item["rotation"] = rotation
    return item


def collate_skipping_corrupt(items: Sequence[dict | None]) -> dict | None:
    """Collate dataset items, dropping the ``None`` of skipped corrupt images.

    The batch gets ``skipped`` (int64 scalar): how many were dropped. ``None`` when all were.
    """
    kept = [item for item in items if item is not None]
    if not kept:
        return None
    batch = default_collate(kept)
    batch["skipped"] = torch.tensor(len(items) - len(kept))
    return batch


@dataclass
class VerifyReport:
    """What a dataset's ``verify`` found: counts per (split, class) against the expected ones,
    files that do not decode, and other problems (missing files, bad labels)."""

    dataset: str
    root: Path
    counts: list[tuple[str, str, int, int | None]] = field(default_factory=list)  # split, class, found, expected
    unreadable: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def count(self, split: str, name: str, found: int, expected: int | None = None) -> None:
        self.counts.append((split, name, int(found), None if expected is None else int(expected)))

    @property
    def mismatches(self) -> list[tuple[str, str, int, int | None]]:
        return [c for c in self.counts if c[3] is not None and c[2] != c[3]]

    @property
    def ok(self) -> bool:
        return not (self.unreadable or self.problems or self.mismatches)

    def decode_files(self, paths, desc: str, progress: bool = True) -> None:
        """Decode every image file of ``paths`` completely (progress bar ``desc``); the ones that do
        not decode are added to :attr:`unreadable`."""
        from tqdm import tqdm

        for path in tqdm(paths, desc=desc, disable=not progress):
            try:
                decode_image(path)
            except CorruptImageError:
                self.unreadable.append(str(path))

    def format(self, max_listed: int = 20) -> str:
        lines = [f"{self.dataset} at {self.root}"]
        if self.counts:
            width = max(len(f"{s}/{c}") for s, c, _, _ in self.counts)
            lines.append(f"  {'split/class':<{width}} {'found':>8} {'expected':>9}")
            for split, name, found, expected in self.counts:
                flag = "" if expected is None or found == expected else "  <-- mismatch"
                exp = "-" if expected is None else str(expected)
                lines.append(f"  {f'{split}/{name}':<{width}} {found:>8} {exp:>9}{flag}")
        for title, items in (("unreadable files", self.unreadable), ("problems", self.problems)):
            if items:
                lines.append(f"  {len(items)} {title}:")
                lines += [f"    {item}" for item in items[:max_listed]]
                if len(items) > max_listed:
                    lines.append(f"    ... and {len(items) - max_listed} more")
        lines += [f"  note: {n}" for n in self.notes]
        lines.append("  OK" if self.ok else "  FAILED")
        return "\n".join(lines)


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


class PoseDataModule(pl.LightningDataModule):
    """The loaders shared by the dataset modules: a seeded per-epoch shuffle for training, the
    dataset order for evaluation, every image kept (no dropped last batch), corrupt images skipped
    by :func:`collate_skipping_corrupt`.

    Subclasses set ``data_train``, ``data_val`` (or ``None``), ``data_test`` in ``setup`` and
    ``batch_size``, ``num_workers``, ``pin_memory``, ``seed`` and ``class_names`` in ``__init__``.
    """

    def _loader(self, dataset, train: bool) -> DataLoader:
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            sampler=EpochShuffleSampler(len(dataset), self.seed, dataset) if train else None,
            shuffle=False,
            drop_last=False,
            num_workers=self.num_workers,
            pin_memory=self.pin_memory,
            persistent_workers=False,
            collate_fn=collate_skipping_corrupt,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, train=True)

    def val_dataloader(self) -> DataLoader | list:
        return self._loader(self.data_val, train=False) if self.data_val is not None else []

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_test, train=False)
