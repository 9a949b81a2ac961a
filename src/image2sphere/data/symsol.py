"""SYMSOL, rendered by this project or downloaded: its Dataset and DataModule.

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

from image2sphere.checks import check_int
from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    load_image,
    missing_dataset_error,
    normalize_images,
    skip_corrupt,
    stable_seed,
)
from image2sphere.data.datamodule import PoseDataModule
from image2sphere.data.loading import EpochDataset, EpochIndex
from image2sphere.data.shapes import SYMSOL_I_SHAPES, check_shape_list
from image2sphere.data.symsol_labels import SYMSOL_DOCS, SYMSOL_URL, load_symsol_rotations

__all__ = ["LABEL_MODES", "SymsolDataModule", "SymsolDataset"]

log = logging.getLogger(__name__)

LABEL_MODES = ("random", "first", "all")


def _shape_tuple(shapes: Sequence[str] | str, key: str) -> tuple[str, ...]:
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
            raise ValueError(f"label must be one of {LABEL_MODES}, got {label!r}")
        self.root = Path(root)
        self.split = split
        self.shapes = _shape_tuple(shapes, "shapes")
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
                raise ValueError(f"rows for {shape!r} must lie in [0, {len(dense)})")
            self.items += [(c, int(r)) for r in use]
            self.rotations.append(torch.from_numpy(dense))
            self.counts.append(torch.from_numpy(counts))
        self.max_m = max(int(counts.max()) for counts in self.counts)
        self._cache: torch.Tensor | None = None
        missing = [p for p in (self.image_path(i) for i in range(len(self.items))) if not p.is_file()]
        if missing:
            raise FileNotFoundError(
                f"{len(missing)} image(s) listed in {split_dir / 'rotations.npz'} are missing, e.g. {missing[0]}"
            )
        if cache_images:
            if self.on_corrupt == "skip":
                raise ValueError("dataset.cache_images needs dataset.on_corrupt=fail (a cache cannot skip images)")
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
        if self.return_all or self.label == "all":
            padded = rotations[:1].expand(self.max_m, 3, 3).clone()
            padded[:count] = rotations[:count]
            item["rotations"] = padded
            item["mask"] = torch.arange(self.max_m) < count
        else:
            j = 0
            if self.label == "random" and count > 1:
                g = torch.Generator().manual_seed(stable_seed("label", self.seed, epoch, c, row))
                j = int(torch.randint(count, (1,), generator=g))
            item["rotation"] = rotations[j].clone()
        return item


class SymsolDataModule(PoseDataModule):
    """SYMSOL train / validation / test loaders.

    Args:
        root: the dataset root. ``None`` with ``render`` set: a cache directory under
            ``render_dir`` named after the render parameters.
        shapes: which shapes, one model for all (SYMSOL I: tet cube icosa cone cyl).
        shape: a single shape instead of ``shapes`` (SYMSOL II trains one model per marked shape:
            ``dataset.shape=cylO``).
        num_views: use only the first this many training images of each shape (``None``: all),
            e.g. 10000 for the paper's low-data SYMSOL experiment. The validation images are
            carved from these.
        val_per_shape: training images per shape held out (chosen with ``seed``) for validation.
        test_per_shape: use only the first this many test images of each shape.
        label: the training labels: one per image, a ``"random"`` equivalent (the paper) or the
            ``"first"``; or ``"all"`` equivalents, whose mean loss is what ``"random"`` optimises in
            expectation, without the noise of drawing one (docs/training_fidelity.md, "Every SYMSOL shape").
        image_size: network input size; images are resized when the files differ.
        batch_size, num_workers, pin_memory: loader settings (evaluation uses the same batch size);
            ``num_workers`` an integer or ``"auto"`` (see :class:`~image2sphere.data.datamodule.PoseDataModule`).
        cache_images: decode all images once into memory (fast for small sets; without it the
            loader workers decode them).
        seed: seed of the validation split, the shuffling and the label choice.
        render: if set, a dict of :func:`image2sphere.data.render.render_symsol` arguments
            (``train``, ``test`` image counts per shape, ``image_size``, ``seed``, ...): the set is
            rendered once into ``root`` by :meth:`prepare_data` and reused afterwards.
        render_dir: where rendered sets are cached when ``root`` is ``None``.
        on_corrupt: ``"fail"`` or ``"skip"`` for images that do not decode.
        multiprocessing_context: how loader workers start, ``"fork"``, ``"forkserver"`` or ``"spawn"``; ``None``:
            ``forkserver`` on Linux (see :class:`~image2sphere.data.datamodule.PoseDataModule`).
    """

    def __init__(
        self,
        root: str | None = None,
        shapes: Sequence[str] | None = SYMSOL_I_SHAPES,
        shape: str | None = None,
        num_views: int | None = None,
        val_per_shape: int = 0,
        test_per_shape: int | None = None,
        label: str = "random",
        image_size: int = 224,
        batch_size: int = 64,
        num_workers: int | str | None = 0,
        pin_memory: bool = False,
        cache_images: bool = False,
        seed: int = 0,
        render: dict | None = None,
        render_dir: str | None = None,
        on_corrupt: str = "fail",
        multiprocessing_context: str | None = None,
    ):
        super().__init__()
        if shape is not None:
            if shapes is not None and list(_shape_tuple(shapes, "dataset.shapes")) != [shape]:
                raise ValueError(
                    f"dataset.shape={shape!r} and dataset.shapes={list(shapes)} disagree: set one of them "
                    "(dataset.shapes=null with dataset.shape)"
                )
            shapes = [shape]
        if shapes is None:
            raise ValueError("set dataset.shapes (a list) or dataset.shape (one shape)")
        self.shapes = _shape_tuple(shapes, "dataset.shapes" if shape is None else "dataset.shape")
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        if label not in LABEL_MODES:
            raise ValueError(f"dataset.label must be one of {LABEL_MODES}, got {label!r}")
        for key, value in (("num_views", num_views), ("test_per_shape", test_per_shape)):
            if value is not None:
                check_int(f"dataset.{key}", value, 1, note=" or null")
        check_int("dataset.val_per_shape", val_per_shape, 0)
        check_int("dataset.batch_size", batch_size, 1)
        self.num_workers = num_workers  # an integer >= 0 or "auto" (checked by PoseDataModule)
        self.multiprocessing_context = multiprocessing_context  # fork, forkserver, spawn or None (checked)
        self.render = dict(render) if render is not None else None
        if root is None:
            if self.render is None or render_dir is None:
                raise ValueError(
                    "dataset.root is not set: point it at a SYMSOL download (the folder holding train/ and "
                    "test/), e.g. dataset.root=/data/symsol, or set dataset.render to render one"
                )
            root = str(Path(render_dir) / self._render_tag())
        self.root = Path(root)
        if self.render is None:
            self._check_present()
        self.num_views = num_views
        self.val_per_shape = val_per_shape
        self.test_per_shape = test_per_shape
        self.label = label
        self.image_size = int(image_size)
        self.batch_size = int(batch_size)
        self.pin_memory = bool(pin_memory)
        self.cache_images = bool(cache_images)
        self.seed = int(seed)
        self.class_names = list(self.shapes)
        self.data_train = self.data_val = self.data_test = None

    def _render_tag(self) -> str:
        """The cache folder's name: every render parameter and the renderer's version, so that a set
        rendered with other parameters or by another version of the renderer is never reused (nor
        deleted: it stays in its own folder)."""
        from image2sphere.data.render import RENDERER_VERSION

        r = dict(self.render)
        shapes = "-".join(r.pop("shapes", self.shapes))
        tag = f"{shapes}_{r.pop('image_size', 224)}px_train{r.pop('train')}_test{r.pop('test')}_seed{r.pop('seed', 0)}"
        output_neutral = ("batch_size", "progress", "png_thread")  # change how, not what, is rendered
        extra = "".join(f"_{key}{value}" for key, value in sorted(r.items()) if key not in output_neutral)
        return f"{tag}{extra}_renderer{RENDERER_VERSION}"

    def _check_present(self) -> None:
        needed = [self.root / split / "rotations.npz" for split in ("train", "test")]
        needed += [self.root / split / "images" for split in ("train", "test")]
        if not all(p.exists() for p in needed):
            missing = [str(p.relative_to(self.root)) for p in needed if not p.exists()] if self.root.is_dir() else []
            raise missing_dataset_error(
                "SYMSOL",
                self.root,
                "the unzipped symsol_dataset.zip: train/ and test/, each with images/{shape}_{i:05d}.png and "
                "rotations.npz" + (f" (missing: {', '.join(missing)})" if missing else ""),
                SYMSOL_URL,
                "dataset.root",
                SYMSOL_DOCS,
            )

    def prepare_data(self) -> None:
        if self.render is None:
            self._check_present()
            return
        from image2sphere.data.render import render_symsol

        r = dict(self.render)
        splits = {"train": r.pop("train"), "test": r.pop("test")}
        r.setdefault("shapes", self.shapes)
        missing = set(self.shapes) - set(r["shapes"])
        if missing:
            raise ValueError(f"dataset.render.shapes lacks {sorted(missing)}, which dataset.shapes uses")
        render_symsol(self.root, splits=splits, **r)

    def _rows(self, rotations, limit: int | None) -> dict[str, np.ndarray]:
        return {s: np.arange(min(len(rotations[s][0]), limit or len(rotations[s][0]))) for s in self.shapes}

    def setup(self, stage: str | None = None) -> None:
        common = dict(
            root=self.root, shapes=self.shapes, image_size=self.image_size, seed=self.seed, on_corrupt=self.on_corrupt
        )
        if stage in (None, "fit", "validate") and self.data_train is None:
            rotations = load_symsol_rotations(self.root / "train", self.shapes)
            rows = self._rows(rotations, self.num_views)
            train_rows, val_rows = {}, {}
            for s, r in rows.items():
                if self.val_per_shape >= len(r):
                    raise ValueError(
                        f"dataset.val_per_shape={self.val_per_shape} leaves no training images of {s!r} "
                        f"({len(r)} available)"
                    )
                g = torch.Generator().manual_seed(stable_seed("val-split", self.seed, s))
                perm = r[torch.randperm(len(r), generator=g).numpy()]
                val_rows[s], train_rows[s] = np.sort(perm[: self.val_per_shape]), np.sort(perm[self.val_per_shape :])
            self.data_train = SymsolDataset(
                split="train", rows=train_rows, label=self.label, cache_images=self.cache_images,
                rotations=rotations, **common,
            )  # fmt: skip
            if self.val_per_shape:
                self.data_val = SymsolDataset(
                    split="train", rows=val_rows, return_all=True, cache_images=self.cache_images,
                    rotations=rotations, **common,
                )  # fmt: skip
        if stage in (None, "test") and self.data_test is None:
            rotations = load_symsol_rotations(self.root / "test", self.shapes)
            self.data_test = SymsolDataset(
                split="test", rows=self._rows(rotations, self.test_per_shape), return_all=True,
                cache_images=self.cache_images, rotations=rotations, **common,
            )  # fmt: skip
