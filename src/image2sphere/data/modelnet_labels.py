"""ModelNet10-SO(3) (Liao et al. 2019) files in their published layout (that of ``ModelNet10-SO3.tar.gz``):
the layout, view ids and the labels (``viewID2quat.pkl``). The images are read by :mod:`image2sphere.data.modelnet`.

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
"""

from __future__ import annotations

import logging
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.data.common import missing_dataset_error
from image2sphere.data.safe_io import load_pickle
from image2sphere.so3.rotations import quaternion_to_matrix

__all__ = [
    "DATASET_NAME",
    "MODELNET10_CLASSES",
    "MODELNET10_SPLITS",
    "MODELNET10_TEST_INSTANCES",
    "MODELNET10_TRAIN_INSTANCES",
    "QUATERNION_FILE",
    "TRAIN_SPLITS",
    "VIEWS_PER_INSTANCE",
    "ModelNet10Labels",
    "check_split_files",
    "lmdb_dir",
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
        raise ConfigError(f"view id {key!r} is not of the form {{class}}_{{instance}}.v{{view}}")
    return cls, instance


# ----------------------------------------------------------------------------------------------
# Labels


def read_quaternion_dict(pkl: Path) -> dict[str, object]:
    """The raw ``viewID2quat.pkl`` dict with ``str`` keys; ``ValueError`` naming the file if unreadable
    (:class:`~image2sphere.data.safe_io.UnsafePickleError` if it asks for anything but numpy arrays and
    plain containers: nothing of it is run)."""
    raw = load_pickle(pkl, encoding="latin1", remedy=f"re-download the dataset from {GET_FROM}")
    if not isinstance(raw, dict):
        raise ConfigError(
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
        raise InputNotFoundError(
            f"ModelNet10-SO(3) labels not found: {pkl} (expected {QUATERNION_FILE} inside every "
            f"{{split}}.Rawjpg.lmdb folder; see {DOCS})"
        )
    raw = read_quaternion_dict(pkl)
    if not raw:
        raise ConfigError(f"{pkl} lists no views (empty dict): re-download the dataset from {GET_FROM}")
    keys, q, problems = quaternion_table(pkl, raw)
    if problems:
        more = f" (and {len(problems) - 1} more)" if len(problems) > 1 else ""
        raise ConfigError(f"{problems[0]}{more}: the file is corrupt; re-download the dataset from {GET_FROM}")
    class_of = {c: i for i, c in enumerate(MODELNET10_CLASSES)}
    class_index = np.empty(len(keys), dtype=np.int64)
    instances = []
    for i, key in enumerate(keys):
        try:
            cls, instance = parse_view_id(key)
        except ValueError as e:
            raise ConfigError(f"{pkl}[{key!r}]: {e}") from None
        if cls not in class_of:
            raise ConfigError(f"{pkl}[{key!r}]: unknown class {cls!r} (known: {', '.join(MODELNET10_CLASSES)})")
        class_index[i] = class_of[cls]
        instances.append(instance)
    rotations = quaternion_wxyz_to_matrix(q).astype(np.float32)
    log.info("%s: %d views of %d instances", pkl, len(keys), len(set(instances)))
    return ModelNet10Labels(directory, keys, instances, class_index, rotations)


def check_split_files(root: Path, splits: Iterable[str]) -> None:
    """Raise :func:`~image2sphere.data.common.missing_dataset_error` unless ``root`` holds the LMDB and
    pickle of every split."""
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
