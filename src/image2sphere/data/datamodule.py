"""The LightningDataModules of the datasets: the base :class:`PoseDataModule` (loaders and worker settings)
and one module per published layout (:class:`SymsolDataModule`, :class:`ModelNet10DataModule`,
:class:`Pascal3DDataModule`).

Workers are persistent, images are decoded in them, each opens its own file handles
(:func:`~image2sphere.data.workers.init_worker`), they start from a fork server by default
(:func:`~image2sphere.data.workers.worker_context`), and memory is pinned only when a CUDA device is present.

This is the one module of :mod:`image2sphere.data` that imports Lightning. The Datasets live in
:mod:`~image2sphere.data.symsol`, :mod:`~image2sphere.data.modelnet` and :mod:`~image2sphere.data.pascal3d`,
which import torch but not Lightning: a loader worker, which unpickles its Dataset, imports only those.
"""

from __future__ import annotations

import logging
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import lightning.pytorch as pl
import numpy as np
import torch
from torch.utils.data import DataLoader

from image2sphere.checks import ConfigError, InputNotFoundError, check_int, check_number
from image2sphere.data.common import check_corrupt_policy, missing_dataset_error, stable_seed
from image2sphere.data.loading import EpochShuffleSampler, PaddedDataset, ShardSampler, collate_skipping_corrupt
from image2sphere.data.modelnet import ModelNet10Dataset, check_lmdb_not_empty
from image2sphere.data.modelnet_labels import (
    GET_FROM,
    MODELNET10_CLASSES,
    MODELNET10_SPLITS,
    TRAIN_SPLITS,
    ModelNet10Labels,
    check_split_files,
    lmdb_dir,
    load_modelnet10_labels,
)
from image2sphere.data.pascal3d import DEFAULT_AUGMENT, Pascal3DDataset, check_augment
from image2sphere.data.pascal3d_annotations import (
    OBJECT_MODES,
    PASCAL3D_CLASSES,
    Pascal3DObject,
    check_classes,
    check_pascal3d_layout,
    check_renderforcnn_layout,
    list_pascal3d_objects,
    list_renderforcnn,
)
from image2sphere.data.shapes import SYMSOL_I_SHAPES
from image2sphere.data.symsol import LABEL_MODES, SymsolDataset, shape_tuple
from image2sphere.data.symsol_labels import SYMSOL_DOCS, SYMSOL_URL, load_symsol_rotations
from image2sphere.data.workers import (
    AUTO,
    DEFAULT_START_METHOD,
    auto_num_workers,
    check_multiprocessing_context,
    check_num_workers,
    init_worker,
    local_processes,
    worker_context,
)

__all__ = ["FolderDataModule", "ModelNet10DataModule", "Pascal3DDataModule", "PoseDataModule", "SymsolDataModule"]

log = logging.getLogger(__name__)


class PoseDataModule(pl.LightningDataModule):
    """The loaders shared by the dataset modules: a seeded per-epoch shuffle for training, the
    dataset order for evaluation, every image kept (no dropped last batch), corrupt images skipped
    by :func:`~image2sphere.data.loading.collate_skipping_corrupt`.

    Workers: ``num_workers`` is set as an integer or ``"auto"``
    (:func:`~image2sphere.data.workers.check_num_workers`) and read as the integer it resolves to
    (:func:`~image2sphere.data.workers.auto_num_workers` with
    :func:`~image2sphere.data.workers.local_processes` of the attached trainer). With workers they are
    persistent (started once per loader, not every epoch), images are decoded in them, and
    :func:`~image2sphere.data.workers.init_worker` runs in each. ``pin_memory`` applies only
    when a CUDA device is present. ``multiprocessing_context`` is how workers start: set as ``"fork"``,
    ``"forkserver"``, ``"spawn"`` or ``None``
    (:func:`~image2sphere.data.workers.check_multiprocessing_context`), read as the method it resolves to
    (``None``: :data:`~image2sphere.data.workers.DEFAULT_START_METHOD`, ``forkserver`` on Linux; ``fork``
    can deadlock a worker at start in a rank with threads, see :mod:`~image2sphere.data.workers`).

    Subclasses set ``data_train``, ``data_val`` (or ``None``), ``data_test`` in ``setup`` and
    ``batch_size``, ``num_workers``, ``multiprocessing_context``, ``pin_memory``, ``seed`` and
    ``class_names`` in ``__init__``.
    """

    _resume: tuple[int, int] | None = None
    _start_epoch: int = 0
    _num_workers: int | str = 0
    _multiprocessing_context: str | None = None

    @property
    def num_workers(self) -> int:
        """Loader workers per loader: the integer set, or what ``auto`` resolves to here."""
        if self._num_workers == AUTO:
            return auto_num_workers(processes=local_processes(getattr(self, "trainer", None)))
        return int(self._num_workers)

    @num_workers.setter
    def num_workers(self, value: int | str | None) -> None:
        self._num_workers = check_num_workers(value)

    @property
    def num_workers_setting(self) -> int | str:
        """``num_workers`` as configured: an integer or ``"auto"``."""
        return self._num_workers

    @property
    def multiprocessing_context(self) -> str:
        """How the workers start: the method set, or the default it resolves to (``forkserver`` on Linux)."""
        return self._multiprocessing_context or DEFAULT_START_METHOD

    @multiprocessing_context.setter
    def multiprocessing_context(self, value: str | None) -> None:
        self._multiprocessing_context = check_multiprocessing_context(value)

    def resume_within_epoch(self, epoch: int, batches_done: int) -> None:
        """Start training in ``epoch`` after its first ``batches_done`` batches (a checkpoint written
        mid-epoch, see :mod:`image2sphere.training.checkpointing`); later epochs are whole."""
        self._resume = (int(epoch), int(batches_done) * int(self.batch_size))

    def start_at_epoch(self, epoch: int) -> None:
        """The training sampler's epoch before Lightning first sets it: the epoch a resumed run starts in.

        Lightning creates the training iterator of a resumed run before it tells the sampler the epoch,
        and does not create it again for that first epoch; loader workers fetch their first indices as the
        iterator is created. Without this, a run resumed in epoch ``e > 0`` with ``num_workers > 0`` would
        train its first epoch on epoch 0's permutation and labels (measured: final weights 1.4 apart from
        the uninterrupted run's; with ``num_workers=0`` the indices are drawn later and were right)."""
        self._start_epoch = int(epoch)

    def _ranks(self) -> tuple[int, int]:
        """``(world size, global rank)`` of the run this module is attached to (``(1, 0)`` outside one)."""
        trainer = getattr(self, "trainer", None)
        if trainer is None or int(getattr(trainer, "world_size", 1)) <= 1:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    def _loader(self, dataset, train: bool) -> DataLoader:
        """A loader of ``dataset``: the seeded per-epoch permutation for training, the dataset's order for
        evaluation; in a distributed run each rank's share of either
        (:class:`~image2sphere.data.loading.EpochShuffleSampler`, :class:`~image2sphere.data.loading.ShardSampler`)."""
        world, rank = self._ranks()
        if train:
            sampler = EpochShuffleSampler(len(dataset), self.seed, dataset, self._resume, world, rank)
            if self._start_epoch:
                sampler.set_epoch(self._start_epoch)
        else:
            sampler = ShardSampler(len(dataset), world, rank) if world > 1 else None
            if sampler is not None:  # the same number of batches on every rank (empty slots at the end)
                dataset = PaddedDataset(dataset, sampler.total_size)
        workers = self.num_workers
        if self._num_workers == AUTO:
            log.info("dataset.num_workers=auto: %d loader workers", workers)
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            shuffle=False,
            drop_last=False,
            num_workers=workers,
            pin_memory=bool(self.pin_memory) and torch.cuda.is_available(),
            persistent_workers=workers > 0,
            worker_init_fn=init_worker if workers > 0 else None,
            multiprocessing_context=worker_context(self._multiprocessing_context) if workers > 0 else None,
            collate_fn=collate_skipping_corrupt,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, train=True)

    def val_dataloader(self) -> DataLoader | list:
        return self._loader(self.data_val, train=False) if self.data_val is not None else []

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_test, train=False)


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
            if shapes is not None and list(shape_tuple(shapes, "dataset.shapes")) != [shape]:
                raise ConfigError(
                    f"dataset.shape={shape!r} and dataset.shapes={list(shapes)} disagree: set one of them "
                    "(dataset.shapes=null with dataset.shape)"
                )
            shapes = [shape]
        if shapes is None:
            raise ConfigError("set dataset.shapes (a list) or dataset.shape (one shape)")
        self.shapes = shape_tuple(shapes, "dataset.shapes" if shape is None else "dataset.shape")
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        if label not in LABEL_MODES:
            raise ConfigError(f"dataset.label must be one of {LABEL_MODES}, got {label!r}")
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
                raise ConfigError(
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
            raise ConfigError(f"dataset.render.shapes lacks {sorted(missing)}, which dataset.shapes uses")
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
                    raise ConfigError(
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


class ModelNet10DataModule(PoseDataModule):
    """ModelNet10-SO(3) train / validation / test loaders.

    Args:
        root: the ``ModelNet10-SO3`` folder (holding the ``*.Rawjpg.lmdb`` directories).
        train_split: ``"train_100V"`` (full, 100 views per instance) or ``"train_20V"`` (limited).
        test_split: the evaluation split, normally ``"test_20V"``.
        val_instances_per_class: object instances per class held out of the training split (chosen
            with ``seed``); all their views form the validation set. 0: no validation.
        image_size: network input size; images are resized when the records differ.
        batch_size, num_workers, pin_memory: loader settings (evaluation uses the same batch size);
            ``num_workers`` an integer or ``"auto"`` (see :class:`~image2sphere.data.datamodule.PoseDataModule`).
        on_corrupt: ``"fail"`` or ``"skip"`` for records that do not decode.
        seed: seed of the validation split and of the shuffling.
        multiprocessing_context: how loader workers start, ``"fork"``, ``"forkserver"`` or ``"spawn"``; ``None``:
            ``forkserver`` on Linux (see :class:`~image2sphere.data.datamodule.PoseDataModule`).

    The constructor checks that the needed files are there, so a wrong ``dataset.root`` fails
    before the model is built.
    """

    def __init__(
        self,
        root: str | Path | None,
        train_split: str = "train_100V",
        test_split: str = "test_20V",
        val_instances_per_class: int = 0,
        image_size: int = 224,
        batch_size: int = 64,
        num_workers: int | str | None = 0,
        pin_memory: bool = False,
        on_corrupt: str = "fail",
        seed: int = 0,
        multiprocessing_context: str | None = None,
    ):
        super().__init__()
        if root is None or str(root) == "":
            raise ConfigError(
                "dataset.root is not set: point it at the unpacked ModelNet10-SO3 folder (holding "
                f"train_100V.Rawjpg.lmdb/ ...), e.g. dataset.root=/data/ModelNet10-SO3; get it from {GET_FROM}"
            )
        if train_split not in TRAIN_SPLITS:
            raise ConfigError(f"dataset.train_split must be one of {TRAIN_SPLITS}, got {train_split!r}")
        if test_split not in MODELNET10_SPLITS:
            raise ConfigError(f"dataset.test_split must be one of {MODELNET10_SPLITS}, got {test_split!r}")
        self.val_instances_per_class = check_int("dataset.val_instances_per_class", val_instances_per_class, 0)
        self.image_size = check_int("dataset.image_size", image_size, 1)
        self.batch_size = check_int("dataset.batch_size", batch_size, 1)
        self.num_workers = num_workers  # an integer >= 0 or "auto" (checked by PoseDataModule)
        self.multiprocessing_context = multiprocessing_context  # fork, forkserver, spawn or None (checked)
        if not isinstance(pin_memory, bool):
            raise ConfigError(f"dataset.pin_memory must be true or false, got {pin_memory!r}")
        self.pin_memory = pin_memory
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ConfigError(f"dataset.seed must be an integer, got {seed!r}")
        self.seed = seed
        self.root = Path(root).expanduser()
        self.train_split = train_split
        self.test_split = test_split
        self.class_names = list(MODELNET10_CLASSES)
        check_split_files(self.root, [train_split, test_split])
        for split in dict.fromkeys([train_split, test_split]):
            check_lmdb_not_empty(lmdb_dir(self.root, split))
        self._labels: dict[str, ModelNet10Labels] = {}
        self.data_train = self.data_val = self.data_test = None

    def labels(self, split: str) -> ModelNet10Labels:
        """The labels of ``split``, read once."""
        if split not in self._labels:
            self._labels[split] = load_modelnet10_labels(lmdb_dir(self.root, split))
        return self._labels[split]

    def split_instances(self, labels: ModelNet10Labels) -> tuple[np.ndarray, np.ndarray]:
        """``(train_rows, val_rows)`` of ``labels``: ``val_instances_per_class`` instances of every
        class (chosen with ``seed``) with all their views go to validation."""
        rows_of: dict[str, list[int]] = defaultdict(list)
        for row, instance in enumerate(labels.instances):
            rows_of[instance].append(row)
        val_rows: list[int] = []
        k = self.val_instances_per_class
        for c, cls in enumerate(MODELNET10_CLASSES):
            instances = sorted({labels.instances[r] for r in np.flatnonzero(labels.class_index == c)})
            if not instances or k == 0:
                continue
            if k >= len(instances):
                raise ConfigError(
                    f"dataset.val_instances_per_class={k} leaves no training instances of {cls!r} "
                    f"({len(instances)} in {labels.path})"
                )
            g = torch.Generator().manual_seed(stable_seed("val-split", self.seed, cls))
            for j in torch.randperm(len(instances), generator=g)[:k].tolist():
                val_rows += rows_of[instances[j]]
        is_val = np.zeros(len(labels), dtype=bool)
        is_val[val_rows] = True
        return np.flatnonzero(~is_val), np.flatnonzero(is_val)

    def setup(self, stage: str | None = None) -> None:
        common = dict(root=self.root, image_size=self.image_size, on_corrupt=self.on_corrupt)
        if stage in (None, "fit", "validate") and self.data_train is None:
            labels = self.labels(self.train_split)
            train_rows, val_rows = self.split_instances(labels)
            self.data_train = ModelNet10Dataset(split=self.train_split, rows=train_rows, labels=labels, **common)
            if len(val_rows):
                self.data_val = ModelNet10Dataset(
                    split=self.train_split, rows=val_rows, return_all=True, labels=labels, **common
                )
            log.info(
                "ModelNet10-SO(3) %s: %d training and %d validation views",
                self.train_split,
                len(train_rows),
                len(val_rows),
            )
        if stage in (None, "test") and self.data_test is None:
            labels = self.labels(self.test_split)
            self.data_test = ModelNet10Dataset(split=self.test_split, return_all=True, labels=labels, **common)


class Pascal3DDataModule(PoseDataModule):
    """PASCAL3D+ train (real + synthetic, augmented) / validation / test loaders.

    Args:
        root: the unpacked ``PASCAL3D+_release1.1``.
        synthetic_root: the RenderForCNN images (``None``: real images only).
        synthetic_ratio: synthetic images per real image in a training epoch (paper: 3).
        objects: ``"first"`` or ``"all"`` (see :mod:`image2sphere.data.pascal3d_annotations`).
        image_size: side of the warped images (224).
        augment: training augmentation (``{"flip", "box_jitter", "roll_std_deg"}``); ``None``: none.
        val_per_class: real training images per class held out (chosen with ``seed``) for validation.
        synthetic_focal: focal length (pixels) assumed for synthetic images.
        batch_size, num_workers, pin_memory: loader settings; ``num_workers`` an integer or ``"auto"``
            (see :class:`~image2sphere.data.datamodule.PoseDataModule`).
        on_corrupt: ``"fail"`` or ``"skip"`` for images that do not decode.
        seed: seed of the validation split, shuffling, augmentation and synthetic draws.
        classes: the categories used (default all 12); ``class_index`` is the position in this list.
        multiprocessing_context: how loader workers start, ``"fork"``, ``"forkserver"`` or ``"spawn"``; ``None``:
            ``forkserver`` on Linux (see :class:`~image2sphere.data.datamodule.PoseDataModule`).
    """

    def __init__(
        self,
        root: str,
        synthetic_root: str | None = None,
        synthetic_ratio: float = 3.0,
        objects: str = "first",
        image_size: int = 224,
        augment: dict | None = DEFAULT_AUGMENT,
        val_per_class: int = 0,
        synthetic_focal: float = 3000.0,
        batch_size: int = 64,
        num_workers: int | str | None = 0,
        pin_memory: bool = False,
        on_corrupt: str = "fail",
        seed: int = 0,
        classes: Sequence[str] = PASCAL3D_CLASSES,
        multiprocessing_context: str | None = None,
    ):
        super().__init__()
        self.classes = check_classes(classes)
        if objects not in OBJECT_MODES:
            raise ConfigError(f"dataset.objects must be one of {OBJECT_MODES}, got {objects!r}")
        check_number("dataset.synthetic_ratio", synthetic_ratio, 0.0)
        check_int("dataset.val_per_class", val_per_class, 0)
        self.num_workers = num_workers  # an integer >= 0 or "auto" (checked by PoseDataModule)
        self.multiprocessing_context = multiprocessing_context  # fork, forkserver, spawn or None (checked)
        check_int("dataset.image_size", image_size, 8)
        check_int("dataset.batch_size", batch_size, 1)
        if not check_number("dataset.synthetic_focal", synthetic_focal) > 0:
            raise ConfigError(f"dataset.synthetic_focal must be > 0, got {synthetic_focal!r}")
        self.augment = check_augment(augment)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        self.root = Path(root)
        check_pascal3d_layout(self.root)
        self.synthetic_root = Path(synthetic_root) if synthetic_root is not None else None
        if self.synthetic_root is not None:
            check_renderforcnn_layout(self.synthetic_root)
        self.synthetic_ratio = float(synthetic_ratio)
        self.objects = objects
        self.image_size = int(image_size)
        self.val_per_class = val_per_class
        self.synthetic_focal = float(synthetic_focal)
        self.batch_size = int(batch_size)
        self.pin_memory = bool(pin_memory)
        self.seed = int(seed)
        self.class_names = list(self.classes)
        self.data_train = self.data_val = self.data_test = None

    def _objects(self, split: str) -> list[Pascal3DObject]:
        objects, dropped = list_pascal3d_objects(self.root, split, self.objects, self.classes)
        log.info("PASCAL3D+ %s: %d objects kept; dropped: %s", split, len(objects), dropped or "none")
        if not objects:
            raise ConfigError(
                f"PASCAL3D+ {split} split at {self.root} has no usable objects (dropped: {dropped or 'none'}); "
                "check the download with: python -m image2sphere.data.verify pascal3d " + str(self.root)
            )
        return objects

    def setup(self, stage: str | None = None) -> None:
        common = dict(image_size=self.image_size, on_corrupt=self.on_corrupt, seed=self.seed)
        if stage in (None, "fit", "validate") and self.data_train is None:
            objects = self._objects("train")
            val_images: set[Path] = set()
            if self.val_per_class:
                for c in range(len(self.classes)):
                    images = sorted({o.image for o in objects if o.class_index == c})
                    g = torch.Generator().manual_seed(stable_seed("val-split", self.seed, c))
                    pick = torch.randperm(len(images), generator=g)[: self.val_per_class].tolist()
                    val_images.update(images[k] for k in pick)
            train = [o for o in objects if o.image not in val_images]
            synthetic = None
            if self.synthetic_root is not None and self.synthetic_ratio > 0:
                synthetic, bad = list_renderforcnn(self.synthetic_root, self.classes)
                if bad:
                    log.warning("%d RenderForCNN file names do not parse and are ignored, e.g. %s", len(bad), bad[0])
                if not synthetic:
                    raise ConfigError(f"no RenderForCNN images found under {self.synthetic_root}")
                log.info("RenderForCNN: %d synthetic images", len(synthetic))
            self.data_train = Pascal3DDataset(
                train, synthetic, self.synthetic_ratio, self.augment, synthetic_focal=self.synthetic_focal, **common
            )
            if val_images:
                val = [o for o in objects if o.image in val_images]
                self.data_val = Pascal3DDataset(val, return_all=True, **common)
        if stage in (None, "test") and self.data_test is None:
            self.data_test = Pascal3DDataset(self._objects("test"), return_all=True, **common)


class FolderDataModule(PoseDataModule):
    """A user's own images and rotations (``dataset=folder``): a folder of images and one labels file
    (:mod:`~image2sphere.data.folder`; docs/datasets.md#your-own-images).

    Args:
        root: the folder; image paths in the labels file are relative to it.
        labels: the labels file (``.csv`` or ``.npz``), relative to ``root``.
        symmetry: ``None``; a group name (``C<n>``, ``D<n>``, ``T``, ``O``, ``I``) for every image; or a group
            per class name. Log likelihood and errors are then taken over every equivalent rotation.
        val_fraction, test_fraction: shares of the images drawn (with ``seed``) into validation and test
            when the labels have no ``split`` column.
        label: the training label among an image's equivalent rotations (as SYMSOL's: ``random``,
            ``first``, ``all``).
        image_size, batch_size, num_workers, pin_memory, multiprocessing_context, on_corrupt, seed: as
            :class:`SymsolDataModule`'s.
    """

    def __init__(
        self,
        root: str,
        labels: str = "labels.csv",
        symmetry: str | dict | None = None,
        val_fraction: float = 0.1,
        test_fraction: float = 0.1,
        label: str = "random",
        image_size: int = 224,
        batch_size: int = 64,
        num_workers: int | str | None = 0,
        pin_memory: bool = False,
        seed: int = 0,
        on_corrupt: str = "fail",
        multiprocessing_context: str | None = None,
    ):
        from image2sphere.data.folder import read_labels, symmetry_groups

        super().__init__()
        self.root = Path(root)
        if not self.root.is_dir():
            raise missing_dataset_error(
                "your images",
                self.root,
                f"a folder of images and its labels file ({labels})",
                "your own data (python -m image2sphere.data.fixtures ROOT writes an example into ROOT/my_poses)",
                "dataset.root",
                "docs/datasets.md#your-own-images",
            )
        for key, value in (("val_fraction", val_fraction), ("test_fraction", test_fraction)):
            if check_number(f"dataset.{key}", value, 0.0) >= 1:
                raise ConfigError(f"dataset.{key} must be a share in [0, 1), got {value!r}")
        if val_fraction + test_fraction >= 1:
            raise ConfigError(
                f"dataset.val_fraction + dataset.test_fraction = {val_fraction + test_fraction:g} leaves no "
                "training images"
            )
        if label not in LABEL_MODES:
            raise ConfigError(f"dataset.label must be one of {LABEL_MODES}, got {label!r}")
        check_int("dataset.batch_size", batch_size, 1)
        self.labels_file = self.root / labels
        self.table = read_labels(self.labels_file)
        self.class_names = sorted(set(self.table.classes)) if self.table.classes is not None else [self.root.name]
        symmetry = dict(symmetry) if hasattr(symmetry, "items") else symmetry  # a per-class mapping from the config
        self.groups = symmetry_groups(symmetry, self.class_names, from_file=self.table.equivalent is not None)
        self.val_fraction, self.test_fraction = float(val_fraction), float(test_fraction)
        self.label, self.image_size, self.batch_size = label, int(image_size), int(batch_size)
        self.num_workers = num_workers
        self.multiprocessing_context = multiprocessing_context
        self.pin_memory, self.seed = bool(pin_memory), int(seed)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        self.splits = self._split()
        self._check_images()
        self._shared: tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None = None
        self.data_train = self.data_val = self.data_test = None

    def _split(self) -> dict[str, np.ndarray]:
        """The rows of each split: the labels' ``split`` column, else a seeded draw of the fractions."""
        n = len(self.table.paths)
        if self.table.splits is not None:
            column = np.asarray(self.table.splits)
            splits = {s: np.flatnonzero(column == s) for s in ("train", "val", "test")}
        else:
            order = torch.randperm(n, generator=torch.Generator().manual_seed(stable_seed("folder", self.seed))).numpy()
            n_val, n_test = round(self.val_fraction * n), round(self.test_fraction * n)
            splits = {"val": np.sort(order[:n_val]), "test": np.sort(order[n_val : n_val + n_test]),
                      "train": np.sort(order[n_val + n_test :])}  # fmt: skip
        for name in ("train", "test"):
            if not len(splits[name]):
                how = "the labels' split column" if self.table.splits is not None else (
                    f"dataset.{name}_fraction" if name == "test" else "the fractions")  # fmt: skip
                raise ConfigError(f"{self.labels_file}: no {name} images ({how} of {n} images)")
        return splits

    def _check_images(self) -> None:
        """Every image is there and its header reads, before anything is written: the first one that is not
        is named with its row."""
        from PIL import Image, UnidentifiedImageError

        for i, path in enumerate(self.table.paths):
            file = self.root / path
            row = f"row {self.table.row(i)}"
            if not file.is_file():
                raise InputNotFoundError(f"{self.labels_file}, {row}: the image {file} does not exist")
            try:
                with Image.open(file) as image:
                    image.size  # noqa: B018 - the header is read
            except (UnidentifiedImageError, OSError) as e:
                raise ConfigError(f"{self.labels_file}, {row}: the image {file} cannot be read ({e})") from None

    def _targets(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Every image's equivalent rotations, their counts and its class index, built once and shared by the
        splits' datasets."""
        from image2sphere.data.folder import equivalent_sets, image_classes

        if self._shared is None:
            sets, counts = equivalent_sets(self.table, self.groups, self.class_names)
            index = {name: c for c, name in enumerate(self.class_names)}
            class_index = torch.tensor([index[name] for name in image_classes(self.table, self.class_names)])
            self._shared = (sets, counts, class_index)
        return self._shared

    def _dataset(self, split: str, train: bool):
        from image2sphere.data.folder import FolderDataset

        return FolderDataset(self.root, self.table.paths, *self._targets(), self.splits[split], label=self.label,
                             return_all=not train, image_size=self.image_size, seed=self.seed,
                             on_corrupt=self.on_corrupt)  # fmt: skip

    def setup(self, stage: str | None = None) -> None:
        if stage in (None, "fit", "validate") and self.data_train is None:
            self.data_train = self._dataset("train", train=True)
            self.data_val = self._dataset("val", train=False) if len(self.splits["val"]) else None
            log.info("%s: %d training, %d validation, %d test images", self.labels_file,
                     *(len(self.splits[s]) for s in ("train", "val", "test")))  # fmt: skip
        if stage in (None, "test") and self.data_test is None:
            self.data_test = self._dataset("test", train=False)
