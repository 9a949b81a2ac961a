"""ModelNet10-SO(3) (Liao et al. 2019): its Dataset, reading the views from the split's LMDB, and DataModule.

The layout, view ids and labels are read by :mod:`image2sphere.data.modelnet_labels`
(docs/datasets.md#modelnet10-so3-layout).

Conventions
-----------
* The LMDB environment is opened lazily, read-only and without locking, once per process, through
  a per-process registry because ``lmdb`` refuses to open one environment twice in a process. An
  environment is never used across processes: a DataLoader worker started with ``fork`` closes the
  copies it inherited (:meth:`ModelNet10Dataset.init_worker`, the loaders' ``worker_init_fn``; and
  again on first read if a loader without it forked) and opens its own; a dataset pickled to a
  ``spawn`` or ``forkserver`` worker carries no environment. :func:`close_lmdb_environments` closes
  them (needed before writing to an environment this process has read).
* No data augmentation (the paper does none on this dataset).

Items
-----
Each item is a dict: ``image`` float32 ``(3, S, S)`` (ImageNet-normalised, grayscale as three equal
channels), ``class_index`` (int64 scalar), ``index`` (int64 scalar, the row in the sorted view ids)
and either ``rotation (3, 3)`` float32 (training) or, for evaluation (``return_all=True``),
``rotations (1, 3, 3)`` with ``mask (1,)`` all True: ModelNet10-SO(3) has one label per image, in
the same format as the multi-label evaluation of SYMSOL. With ``on_corrupt="skip"`` an image that
does not decode gives ``None`` (dropped by :func:`~image2sphere.data.loading.collate_skipping_corrupt`).
"""

from __future__ import annotations

import logging
import os
from collections import defaultdict
from collections.abc import Sequence
from pathlib import Path

import lmdb
import numpy as np
import torch
from torch.utils.data import Dataset

from image2sphere.checks import check_int
from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    load_image,
    skip_corrupt,
    stable_seed,
)
from image2sphere.data.datamodule import PoseDataModule
from image2sphere.data.loading import single_label_item
from image2sphere.data.modelnet_labels import (
    GET_FROM,
    MODELNET10_CLASSES,
    MODELNET10_SPLITS,
    QUATERNION_FILE,
    TRAIN_SPLITS,
    ModelNet10Labels,
    check_split_files,
    lmdb_dir,
    load_modelnet10_labels,
)
from image2sphere.data.safe_io import open_lmdb

__all__ = [
    "ModelNet10DataModule",
    "ModelNet10Dataset",
    "MissingRecordError",
    "close_inherited_lmdb_environments",
    "close_lmdb_environments",
    "lmdb_environment",
]

log = logging.getLogger(__name__)

REMEDY = f"re-extract ModelNet10-SO3.tar.gz (re-download it from {GET_FROM} if the archive itself is short)"


# ----------------------------------------------------------------------------------------------
# LMDB environments: one per path and process


_ENVIRONMENTS: dict[str, tuple[int, lmdb.Environment]] = {}


def lmdb_environment(path: Path) -> lmdb.Environment:
    """The read-only environment at ``path`` for this process, opened on first use.

    ``lmdb`` refuses to open an environment twice in one process, and one inherited over ``fork``
    (a DataLoader worker) counts as open: that copy is closed first (the parent's stays open).
    """
    key = str(Path(path).resolve())
    pid = os.getpid()
    entry = _ENVIRONMENTS.get(key)
    if entry is not None:
        owner, env = entry
        if owner == pid:
            return env
        env.close()
    env = open_lmdb(key, REMEDY)  # refuses a truncated data.mdb (reading one would end in SIGBUS)
    _ENVIRONMENTS[key] = (pid, env)
    return env


def close_inherited_lmdb_environments() -> None:
    """Close the environments this process inherited through ``fork`` (opened by its parent); its own
    stay open. Run in every DataLoader worker at start (:meth:`ModelNet10Dataset.init_worker`)."""
    pid = os.getpid()
    for key, (owner, env) in list(_ENVIRONMENTS.items()):
        if owner != pid:
            env.close()  # this process's copy only: the parent's stays open
            del _ENVIRONMENTS[key]


def close_lmdb_environments() -> None:
    """Close the LMDB environments this module opened in this process (a later read reopens them)."""
    pid = os.getpid()
    for key, (owner, env) in list(_ENVIRONMENTS.items()):
        if owner == pid:
            env.close()
        del _ENVIRONMENTS[key]


def _check_lmdb_not_empty(directory: Path) -> int:
    """The number of records of the LMDB at ``directory``; ``ValueError`` naming it when there are none."""
    entries = int(lmdb_environment(directory).stat()["entries"])
    if entries == 0:
        raise ValueError(
            f"{directory} is an empty LMDB (no records): the download or unpacking was incomplete; "
            f"re-download {GET_FROM} or point dataset.root at a complete copy"
        )
    return entries


# ----------------------------------------------------------------------------------------------
# Dataset and DataModule


class MissingRecordError(KeyError):
    """A view id listed in ``viewID2quat.pkl`` that has no record in the split's LMDB."""

    def __str__(self) -> str:  # KeyError would print the repr of the message
        return str(self.args[0])


class ModelNet10Dataset(Dataset):
    """The views of one ModelNet10-SO(3) split (see the module docstring for the item format).

    Args:
        root: the ``ModelNet10-SO3`` folder.
        split: ``"train_100V"``, ``"train_20V"`` or ``"test_20V"``.
        rows: rows of the sorted view ids to use (default: all).
        return_all: return ``rotations (1, 3, 3)`` and ``mask (1,)`` (evaluation) instead of ``rotation``.
        image_size: images are resized to this square size when they differ.
        on_corrupt: ``"fail"`` (raise :class:`~image2sphere.data.common.CorruptImageError`) or
            ``"skip"`` (log once and return ``None``) for a record that does not decode.
        labels: the split's labels if already loaded
            (:func:`~image2sphere.data.modelnet_labels.load_modelnet10_labels`).
    """

    def __init__(
        self,
        root: str | Path,
        split: str,
        rows: Sequence[int] | np.ndarray | None = None,
        return_all: bool = False,
        image_size: int = 224,
        on_corrupt: str = "fail",
        labels: ModelNet10Labels | None = None,
    ):
        if split not in MODELNET10_SPLITS:
            raise ValueError(f"split must be one of {MODELNET10_SPLITS}, got {split!r}")
        self.root = Path(root)
        self.split = split
        self.lmdb_dir = lmdb_dir(self.root, split)
        self.return_all = bool(return_all)
        self.image_size = int(image_size)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "on_corrupt")
        if labels is None:
            check_split_files(self.root, [split])
            _check_lmdb_not_empty(self.lmdb_dir)
            labels = load_modelnet10_labels(self.lmdb_dir)
        self.labels = labels
        self.rows = np.arange(len(labels)) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(self.rows) and (self.rows.min() < 0 or self.rows.max() >= len(labels)):
            raise ValueError(f"rows must lie in [0, {len(labels)}) for {self.lmdb_dir}")
        self._env: lmdb.Environment | None = None
        self._pid: int | None = None
        self._warned: set[str] = set()

    def __getstate__(self) -> dict:
        state = self.__dict__.copy()
        state["_env"] = state["_pid"] = None  # environments do not pickle; each process opens its own
        return state

    def init_worker(self) -> None:
        """Run in a DataLoader worker when it starts (:func:`~image2sphere.data.workers.init_worker`):
        forget the environments inherited through ``fork``; the first read opens this worker's own."""
        close_inherited_lmdb_environments()
        self._env = self._pid = None

    def _record(self, key: str) -> bytes:
        if self._env is None or self._pid != os.getpid():
            self._env = lmdb_environment(self.lmdb_dir)
            self._pid = os.getpid()
        with self._env.begin(buffers=False) as txn:
            data = txn.get(key.encode())
        if data is None:
            raise MissingRecordError(
                f"{self.lmdb_dir} has no record {key!r}, which {self.lmdb_dir / QUATERNION_FILE} lists: the LMDB "
                f"is incomplete; re-download {GET_FROM} "
                f"(python -m image2sphere.data.verify modelnet10 {self.root} lists every such key)"
            )
        return data

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, i: int) -> dict[str, torch.Tensor] | None:
        row = int(self.rows[i])
        key = self.labels.keys[row]
        name = f"{self.lmdb_dir}:{key}"
        try:
            image = load_image(self._record(key), self.image_size, name=name)
        except CorruptImageError as e:
            skip_corrupt(e, self.on_corrupt, self._warned)
            return None
        return single_label_item(image, self.labels.class_index[row], row, self.labels.rotations[row], self.return_all)


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
            raise ValueError(
                "dataset.root is not set: point it at the unpacked ModelNet10-SO3 folder (holding "
                f"train_100V.Rawjpg.lmdb/ ...), e.g. dataset.root=/data/ModelNet10-SO3; get it from {GET_FROM}"
            )
        if train_split not in TRAIN_SPLITS:
            raise ValueError(f"dataset.train_split must be one of {TRAIN_SPLITS}, got {train_split!r}")
        if test_split not in MODELNET10_SPLITS:
            raise ValueError(f"dataset.test_split must be one of {MODELNET10_SPLITS}, got {test_split!r}")
        self.val_instances_per_class = check_int("dataset.val_instances_per_class", val_instances_per_class, 0)
        self.image_size = check_int("dataset.image_size", image_size, 1)
        self.batch_size = check_int("dataset.batch_size", batch_size, 1)
        self.num_workers = num_workers  # an integer >= 0 or "auto" (checked by PoseDataModule)
        self.multiprocessing_context = multiprocessing_context  # fork, forkserver, spawn or None (checked)
        if not isinstance(pin_memory, bool):
            raise ValueError(f"dataset.pin_memory must be true or false, got {pin_memory!r}")
        self.pin_memory = pin_memory
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        if isinstance(seed, bool) or not isinstance(seed, int):
            raise ValueError(f"dataset.seed must be an integer, got {seed!r}")
        self.seed = seed
        self.root = Path(root).expanduser()
        self.train_split = train_split
        self.test_split = test_split
        self.class_names = list(MODELNET10_CLASSES)
        check_split_files(self.root, [train_split, test_split])
        for split in dict.fromkeys([train_split, test_split]):
            _check_lmdb_not_empty(lmdb_dir(self.root, split))
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
                raise ValueError(
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
