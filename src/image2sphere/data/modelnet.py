"""ModelNet10-SO(3) (Liao et al. 2019): its Dataset, reading the views from the split's LMDB (the DataModule
is in :mod:`image2sphere.data.datamodule`).

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
from collections.abc import Sequence
from pathlib import Path

import lmdb
import numpy as np
import torch
from torch.utils.data import Dataset

from image2sphere.checks import ConfigError
from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    load_image,
    skip_corrupt,
)
from image2sphere.data.loading import single_label_item
from image2sphere.data.modelnet_labels import (
    GET_FROM,
    MODELNET10_SPLITS,
    QUATERNION_FILE,
    ModelNet10Labels,
    check_split_files,
    lmdb_dir,
    load_modelnet10_labels,
)
from image2sphere.data.safe_io import open_lmdb

__all__ = [
    "ModelNet10Dataset",
    "MissingRecordError",
    "check_lmdb_not_empty",
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


def check_lmdb_not_empty(directory: Path) -> int:
    """The number of records of the LMDB at ``directory``; ``ValueError`` naming it when there are none."""
    entries = int(lmdb_environment(directory).stat()["entries"])
    if entries == 0:
        raise ConfigError(
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
            raise ConfigError(f"split must be one of {MODELNET10_SPLITS}, got {split!r}")
        self.root = Path(root)
        self.split = split
        self.lmdb_dir = lmdb_dir(self.root, split)
        self.return_all = bool(return_all)
        self.image_size = int(image_size)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "on_corrupt")
        if labels is None:
            check_split_files(self.root, [split])
            check_lmdb_not_empty(self.lmdb_dir)
            labels = load_modelnet10_labels(self.lmdb_dir)
        self.labels = labels
        self.rows = np.arange(len(labels)) if rows is None else np.asarray(rows, dtype=np.int64).reshape(-1)
        if len(self.rows) and (self.rows.min() < 0 or self.rows.max() >= len(labels)):
            raise ConfigError(f"rows must lie in [0, {len(labels)}) for {self.lmdb_dir}")
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
