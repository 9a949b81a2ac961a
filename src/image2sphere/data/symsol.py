"""SYMSOL, rendered by this project or downloaded: its Dataset (the DataModule is in
:mod:`image2sphere.data.datamodule`).

The layout (docs/datasets.md#symsol-layout) and the reading of ``rotations.npz`` are in
:mod:`image2sphere.data.symsol_labels`; a set is rendered by :mod:`image2sphere.data.render`.

Items
-----
Each item is a dict: ``image`` float32 ``(3, S, S)`` (ImageNet-normalised), ``class_index`` (the
shape's position in ``shapes``), ``index`` (row in the npz), and either ``rotation (3, 3)`` (one
training label: a random equivalent, or the rendering rotation, see ``label``) or, for evaluation,
``rotations (M_max, 3, 3)`` with ``mask (M_max,)`` over the full equivalent set (padding repeats
the rendering rotation and is masked out).
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    load_image,
    normalize_images,
    skip_corrupt,
    stable_seed,
)
from image2sphere.data.loading import EpochDataset, EpochIndex
from image2sphere.data.shapes import check_shape_list
from image2sphere.data.symsol_labels import load_symsol_rotations

__all__ = ["LABEL_MODES", "SymsolDataset", "rotation_fields", "shape_tuple"]

log = logging.getLogger(__name__)

LABEL_MODES = ("random", "first", "all")


def shape_tuple(shapes: Sequence[str] | str, key: str) -> tuple[str, ...]:
    """Validated shape names; a single name is accepted for one shape (e.g. ``dataset.shapes=cube``)."""
    return tuple(check_shape_list([shapes] if isinstance(shapes, str) else list(shapes), key))


class SymsolDataset(EpochDataset):
    """Images and rotations of some SYMSOL shapes in one split.

    Items take an index (in the epoch of the last :meth:`set_epoch`) or an
    :class:`~image2sphere.data.loading.EpochIndex` ``(epoch, index)``, what the training sampler
    yields so that the random label choice follows the epoch in DataLoader workers too.

    Args:
        root: the dataset root (holding ``train/`` and ``test/``).
        split: ``"train"`` or ``"test"``.
        shapes: shape names; ``class_index`` is the position in this list.
        rows: per shape, the npz rows to use (default: all).
        label: ``"random"`` (a uniformly chosen equivalent rotation, redrawn every epoch; I2S),
            ``"first"`` (the rendering rotation; IPDF) or ``"all"`` (every equivalent rotation with a
            mask, as ``return_all``: the training loss is then its mean over them, the expectation of the
            ``"random"`` label's loss without its sampling noise). Only used when ``return_all`` is False.
        return_all: return the full equivalent set with a mask (evaluation) instead of one label.
        image_size: images are resized to this square size when they differ.
        cache_images: decode every image once, up front in this process, and keep them in memory
            (uint8, ``N * S * S * 3`` bytes; shared with the workers: inherited through ``fork``, as shared
            memory under ``forkserver`` or ``spawn``). Otherwise images are decoded
            by ``__getitem__``, in the DataLoader workers.
        seed: seed of the label choice.
        on_corrupt: ``"fail"`` (raise, naming the file) or ``"skip"`` (log it; the item is ``None``
            and :func:`image2sphere.data.loading.collate_skipping_corrupt` drops and counts it).
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        shapes: Sequence[str],
        rows: dict[str, np.ndarray] | None = None,
        label: str = "random",
        return_all: bool = False,
        image_size: int = 224,
        cache_images: bool = False,
        seed: int = 0,
        rotations: dict[str, tuple[np.ndarray, np.ndarray]] | None = None,
        on_corrupt: str = "fail",
    ):
        if label not in LABEL_MODES:
            raise ConfigError(f"label must be one of {LABEL_MODES}, got {label!r}")
        self.root = Path(root)
        self.split = split
        self.shapes = shape_tuple(shapes, "shapes")
        self.label = label
        self.return_all = return_all
        self.image_size = int(image_size)
        self.seed = int(seed)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        self.epoch = 0
        self._warned: set[str] = set()
        split_dir = self.root / split
        rotations = rotations if rotations is not None else load_symsol_rotations(split_dir, self.shapes)
        self.items: list[tuple[int, int]] = []  # (class_index, row)
        self.rotations: list[torch.Tensor] = []
        self.counts: list[torch.Tensor] = []
        for c, shape in enumerate(self.shapes):
            dense, counts = rotations[shape]
            use = np.arange(len(dense)) if rows is None else np.asarray(rows[shape])
            if len(use) and (use.min() < 0 or use.max() >= len(dense)):
                raise ConfigError(f"rows for {shape!r} must lie in [0, {len(dense)})")
            self.items += [(c, int(r)) for r in use]
            self.rotations.append(torch.from_numpy(dense))
            self.counts.append(torch.from_numpy(counts))
        self.max_m = max(int(counts.max()) for counts in self.counts)
        self._cache: torch.Tensor | None = None
        missing = [p for p in (self.image_path(i) for i in range(len(self.items))) if not p.is_file()]
        if missing:
            raise InputNotFoundError(
                f"{len(missing)} image(s) listed in {split_dir / 'rotations.npz'} are missing, e.g. {missing[0]}"
            )
        if cache_images:
            if self.on_corrupt == "skip":
                raise ConfigError("dataset.cache_images needs dataset.on_corrupt=fail (a cache cannot skip images)")
            self._cache = torch.stack([self._read(i) for i in range(len(self.items))])

    def image_path(self, i: int) -> Path:
        c, row = self.items[i]
        return self.root / self.split / "images" / f"{self.shapes[c]}_{row:05d}.png"

    def _read(self, i: int) -> torch.Tensor:
        return load_image(self.image_path(i), self.image_size)

    def __len__(self) -> int:
        return len(self.items)

    def __getitem__(self, key: int | EpochIndex) -> dict[str, torch.Tensor] | None:
        epoch, i = self.epoch_and_index(key)
        c, row = self.items[i]
        try:
            image = self._cache[i] if self._cache is not None else self._read(i)
        except CorruptImageError as e:
            skip_corrupt(e, self.on_corrupt, self._warned)
            return None
        item = {
            "image": normalize_images(image),
            "class_index": torch.tensor(c),
            "index": torch.tensor(row),
        }
        rotations, count = self.rotations[c][row], int(self.counts[c][row])
        item.update(
            rotation_fields(rotations, count, self.max_m, self.label, self.return_all, (self.seed, epoch, c, row))
        )
        return item


def rotation_fields(rotations: torch.Tensor, count: int, max_m: int, label: str, return_all: bool,
                    seed: tuple) -> dict[str, torch.Tensor]:  # fmt: skip
    """An item's rotation fields from its ``count`` equivalent rotations ``rotations (>= count, 3, 3)`` (element
    0 its label): the set ``rotations (max_m, 3, 3)`` padded with element 0, and ``mask (max_m,)``, for
    evaluation (``return_all``) or ``label="all"``; else one ``rotation (3, 3)``, element 0 (``"first"``) or
    one drawn with ``seed`` (its epoch in it: redrawn every epoch) for ``"random"``."""
    if return_all or label == "all":
        padded = rotations[:1].expand(max_m, 3, 3).clone()
        padded[:count] = rotations[:count]
        return {"rotations": padded, "mask": torch.arange(max_m) < count}
    j = 0
    if label == "random" and count > 1:
        g = torch.Generator().manual_seed(stable_seed("label", *seed))
        j = int(torch.randint(count, (1,), generator=g))
    return {"rotation": rotations[j].clone()}
