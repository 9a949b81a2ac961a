"""ModelNet10-SO(3) (Liao et al. 2019) in its published layout (that of ``ModelNet10-SO3.tar.gz``).

Layout (docs/datasets.md#modelnet10-so3-layout)
-----------------------------------------------
``{root}/{split}.Rawjpg.lmdb/`` for ``split`` in ``train_100V`` (100 views per training instance,
the paper's full training set), ``train_20V`` (20 views, the "limited" set) and ``test_20V``. Each
is an LMDB environment directory (``data.mdb``, optionally ``lock.mdb``) whose keys are view ids
such as ``bathtub_0107.v001`` and whose values are the JPEG bytes of one view (224x224, three equal
channels), plus ``viewID2quat.pkl``: a dict view id -> quaternion, pickled under Python 2 and read
with ``encoding="latin1"`` (values may be numpy arrays, tuples or lists). ``root`` is the unpacked
``ModelNet10-SO3`` folder. The pickle is read with :func:`image2sphere.data.safe_io.load_pickle`,
which rebuilds numpy arrays and plain containers only (a file asking for anything else is refused,
nothing of it runs), and an LMDB whose ``data.mdb`` is shorter than its header says is refused when
opened (:func:`image2sphere.data.safe_io.open_lmdb`) rather than crashing the process later.

A view id is ``{instance}.v{j:03d}`` with ``instance = {class}_{k:04d}``: the class is the text
before the last ``_`` (``night_stand_0012.v003`` is ``night_stand``), the object instance the text
before the last ``.``. ``class_index`` is the position in :data:`MODELNET10_CLASSES`.

Conventions
-----------
* Quaternions are stored scalar-first, ``(w, x, y, z)``; they are converted once at load time with
  :func:`quaternion_wxyz_to_matrix` (``q`` and ``-q`` give the same matrix). A stored quaternion
  whose norm differs from 1 by more than ``1e-3`` (or is NaN or inf) is rejected; the others are
  normalised.
* The matrix ``R`` of the stored quaternion is used as is (no transpose): ``x_camera = R @ x_object``,
  the convention of the whole project.
* The views of a split are ordered by sorted view id; ``index`` is the row in that order.
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
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from pathlib import Path

import lmdb
import numpy as np
import torch
from torch.utils.data import Dataset

from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    load_image,
    missing_dataset_error,
    skip_corrupt,
    stable_seed,
)
from image2sphere.data.datamodule import PoseDataModule
from image2sphere.data.loading import single_label_item
from image2sphere.data.safe_io import load_pickle, open_lmdb
from image2sphere.so3.rotations import quaternion_to_matrix

__all__ = [
    "MODELNET10_CLASSES",
    "MODELNET10_SPLITS",
    "MODELNET10_TEST_INSTANCES",
    "MODELNET10_TRAIN_INSTANCES",
    "ModelNet10DataModule",
    "ModelNet10Dataset",
    "ModelNet10Labels",
    "MissingRecordError",
    "close_inherited_lmdb_environments",
    "close_lmdb_environments",
    "lmdb_dir",
    "lmdb_environment",
    "load_modelnet10_labels",
    "parse_view_id",
    "quaternion_table",
    "quaternion_wxyz_to_matrix",
    "read_quaternion_dict",
]

log = logging.getLogger(__name__)

MODELNET10_CLASSES = (
    "bathtub", "bed", "chair", "desk", "dresser", "monitor", "night_stand", "sofa", "table", "toilet",
)  # fmt: skip
MODELNET10_SPLITS = ("train_100V", "train_20V", "test_20V")
TRAIN_SPLITS = ("train_100V", "train_20V")
VIEWS_PER_INSTANCE = {"train_100V": 100, "train_20V": 20}
# Object instances per class in ModelNet10's standard train / test split, which ModelNet10-SO(3) keeps.
MODELNET10_TRAIN_INSTANCES = {
    "bathtub": 106, "bed": 515, "chair": 889, "desk": 200, "dresser": 200,
    "monitor": 465, "night_stand": 200, "sofa": 680, "table": 392, "toilet": 344,
}  # fmt: skip
MODELNET10_TEST_INSTANCES = {
    "bathtub": 50, "bed": 100, "chair": 100, "desk": 86, "dresser": 86,
    "monitor": 100, "night_stand": 86, "sofa": 100, "table": 100, "toilet": 100,
}  # fmt: skip
QUATERNION_FILE = "viewID2quat.pkl"
QUATERNION_NORM_TOL = 1e-3
DATASET_NAME = "ModelNet10-SO(3)"
GET_FROM = (
    "http://isis-data.science.uva.nl/shuai/datasets/ModelNet10-SO3.tar.gz "
    "(linked from github.com/leoshine/Spherical_Regression)"
)
DOCS = "docs/datasets.md#modelnet10-so3-layout"
REMEDY = f"re-extract ModelNet10-SO3.tar.gz (re-download it from {GET_FROM} if the archive itself is short)"


def lmdb_dir(root: str | Path, split: str) -> Path:
    """``{root}/{split}.Rawjpg.lmdb``."""
    return Path(root) / f"{split}.Rawjpg.lmdb"


def quaternion_wxyz_to_matrix(q: np.ndarray) -> np.ndarray:
    """Rotation matrices ``(..., 3, 3)`` (float64) of scalar-first quaternions ``(..., 4)`` = ``(w, x, y, z)``,
    through :func:`image2sphere.so3.rotations.quaternion_to_matrix` (normalised; ``q`` and ``-q`` give
    the same matrix; ``ValueError`` for a last dimension other than 4 or a zero or non-finite quaternion).
    """
    return quaternion_to_matrix(torch.as_tensor(np.asarray(q, dtype=np.float64)), order="wxyz").numpy()


def parse_view_id(key: str) -> tuple[str, str]:
    """``(class, instance)`` of a view id: ``"night_stand_0012.v003"`` -> ``("night_stand", "night_stand_0012")``.

    Raises ``ValueError`` when the id lacks the ``.`` or ``_`` of ``{class}_{k}.v{j}``. The class is
    not checked against :data:`MODELNET10_CLASSES`.
    """
    instance, dot, view = key.rpartition(".")
    cls, underscore, number = instance.rpartition("_")
    if not (dot and underscore and cls and number and view):
        raise ValueError(f"view id {key!r} is not of the form {{class}}_{{instance}}.v{{view}}")
    return cls, instance


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
# Labels


def read_quaternion_dict(pkl: Path) -> dict[str, object]:
    """The raw ``viewID2quat.pkl`` dict with ``str`` keys; ``ValueError`` naming the file if unreadable
    (:class:`~image2sphere.data.safe_io.UnsafePickleError` if it asks for anything but numpy arrays and
    plain containers: nothing of it is run)."""
    raw = load_pickle(pkl, encoding="latin1", remedy=f"re-download the dataset from {GET_FROM}")
    if not isinstance(raw, dict):
        raise ValueError(
            f"{pkl} must hold a dict view id -> quaternion (w, x, y, z), got {type(raw).__name__} (see {DOCS})"
        )
    return {(k.decode("latin1") if isinstance(k, bytes) else str(k)): v for k, v in raw.items()}


def quaternion_table(pkl: Path, raw: dict[str, object]) -> tuple[list[str], np.ndarray, list[str]]:
    """Sorted keys, their quaternions ``(N, 4)`` normalised (NaN rows where invalid) and the problems
    found (wrong shape, NaN or inf, norm off by more than :data:`QUATERNION_NORM_TOL`), each naming the key."""
    keys = sorted(raw)
    q: np.ndarray | None
    try:
        q = np.asarray([raw[k] for k in keys], dtype=np.float64)
    except (ValueError, TypeError):
        q = None
    problems = []
    shape_ok = np.ones(len(keys), dtype=bool)
    if q is None or q.shape != (len(keys), 4):
        q = np.full((len(keys), 4), np.nan)
        for i, k in enumerate(keys):
            try:
                v = np.asarray(raw[k], dtype=np.float64)
            except (ValueError, TypeError):
                v = np.asarray(())
            if v.shape == (4,):
                q[i] = v
            else:
                shape_ok[i] = False
                problems.append(f"{pkl}[{k!r}]: quaternion must be 4 numbers (w, x, y, z), got {raw[k]!r:.80}")
    finite = np.isfinite(q).all(axis=1)
    norms = np.linalg.norm(np.where(finite[:, None], q, 0.0), axis=1)
    for i in np.flatnonzero(shape_ok & ~finite):
        problems.append(f"{pkl}[{keys[i]!r}]: quaternion {q[i].tolist()} holds NaN or inf")
    bad = shape_ok & finite & (np.abs(norms - 1) > QUATERNION_NORM_TOL)  # NaN and inf are caught above
    for i in np.flatnonzero(bad):
        problems.append(
            f"{pkl}[{keys[i]!r}]: quaternion {q[i].tolist()} has norm {norms[i]:.6g}, which differs from 1 by "
            f"more than {QUATERNION_NORM_TOL:g}"
        )
    bad |= shape_ok & ~finite
    invalid = ~shape_ok | bad
    q[invalid] = np.nan
    q[~invalid] /= norms[~invalid, None]
    return keys, q, problems


@dataclass(frozen=True)
class ModelNet10Labels:
    """The labels of one split, ordered by sorted view id.

    ``keys`` the view ids, ``instances`` their object instance ids, ``class_index (N,)`` int64 and
    ``rotations (N, 3, 3)`` float32 (``x_camera = R @ x_object``); ``path`` the LMDB directory.
    """

    path: Path
    keys: list[str]
    instances: list[str]
    class_index: np.ndarray
    rotations: np.ndarray

    def __len__(self) -> int:
        return len(self.keys)


def load_modelnet10_labels(directory: str | Path) -> ModelNet10Labels:
    """Read ``{directory}/viewID2quat.pkl`` (``directory`` a ``{split}.Rawjpg.lmdb`` folder).

    Raises ``FileNotFoundError`` for a missing file and ``ValueError`` naming the file (and the key)
    for an unreadable or empty pickle, a view id that does not parse or names an unknown class, and
    a quaternion of the wrong length, holding NaN or inf, or with a norm off by more than ``1e-3``; a
    pickle that asks for anything but numpy arrays and plain containers is refused unrun.
    """
    directory = Path(directory)
    pkl = directory / QUATERNION_FILE
    if not pkl.is_file():
        raise FileNotFoundError(
            f"ModelNet10-SO(3) labels not found: {pkl} (expected {QUATERNION_FILE} inside every "
            f"{{split}}.Rawjpg.lmdb folder; see {DOCS})"
        )
    raw = read_quaternion_dict(pkl)
    if not raw:
        raise ValueError(f"{pkl} lists no views (empty dict): re-download the dataset from {GET_FROM}")
    keys, q, problems = quaternion_table(pkl, raw)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ValueError(f"{problems[0]}{more}: the file is corrupt; re-download the dataset from {GET_FROM}")
    class_of = {c: i for i, c in enumerate(MODELNET10_CLASSES)}
    class_index = np.empty(len(keys), dtype=np.int64)
    instances = []
    for i, key in enumerate(keys):
        try:
            cls, instance = parse_view_id(key)
        except ValueError as e:
            raise ValueError(f"{pkl}[{key!r}]: {e}") from None
        if cls not in class_of:
            raise ValueError(f"{pkl}[{key!r}]: unknown class {cls!r} (known: {', '.join(MODELNET10_CLASSES)})")
        class_index[i] = class_of[cls]
        instances.append(instance)
    rotations = quaternion_wxyz_to_matrix(q).astype(np.float32)
    log.info("%s: %d views of %d instances", pkl, len(keys), len(set(instances)))
    return ModelNet10Labels(directory, keys, instances, class_index, rotations)


def _check_split_files(root: Path, splits: Iterable[str]) -> None:
    """Raise :func:`missing_dataset_error` unless ``root`` holds the LMDB and pickle of every split."""
    splits = list(dict.fromkeys(splits))
    wanted = ", ".join(f"{s}.Rawjpg.lmdb/" for s in splits)
    expected = f"the unpacked ModelNet10-SO3 folder holding {wanted} (each with data.mdb and {QUATERNION_FILE})"
    if (root / "ModelNet10-SO3").is_dir():
        expected += f"; {root / 'ModelNet10-SO3'} exists: did you mean that folder?"
    if not root.is_dir():
        raise missing_dataset_error(DATASET_NAME, root, expected, GET_FROM, "dataset.root", DOCS)
    missing = [
        str(lmdb_dir(root, s) / name)
        for s in splits
        for name in ("data.mdb", QUATERNION_FILE)
        if not (lmdb_dir(root, s) / name).is_file()
    ]
    if missing:
        raise missing_dataset_error(
            DATASET_NAME, root, f"{expected}; missing: {', '.join(missing)}", GET_FROM, "dataset.root", DOCS
        )


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
        labels: the split's labels if already loaded (:func:`load_modelnet10_labels`).
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
            _check_split_files(self.root, [split])
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


def _check_int(value: object, key: str, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{key} must be an integer >= {minimum}, got {value!r}")
    return value


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
        self.val_instances_per_class = _check_int(val_instances_per_class, "dataset.val_instances_per_class", 0)
        self.image_size = _check_int(image_size, "dataset.image_size", 1)
        self.batch_size = _check_int(batch_size, "dataset.batch_size", 1)
        self.num_workers = num_workers  # an integer >= 0 or "auto" (checked by PoseDataModule)
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
        _check_split_files(self.root, [train_split, test_split])
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
