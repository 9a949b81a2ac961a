"""A user's own images and poses: a folder of images and one labels file (``dataset=folder``; the DataModule is
:class:`~image2sphere.data.datamodule.FolderDataModule`). The format is in docs/datasets.md#your-own-images.

Conventions
-----------
* A label is the rotation ``R`` with ``x_camera = R @ x_object`` (column vectors; docs/conventions.md), as
  for every dataset of the project.
* The labels file is a CSV with a header, one row per image: ``image`` (a path relative to the folder),
  then the rotation as a unit quaternion whose component order the header names (``qw,qx,qy,qz`` or
  ``qx,qy,qz,qw``) or as the nine entries of ``R`` row by row (``r00,r01,r02,r10,...,r22``); optional
  ``class`` (a name) and ``split`` (``train``, ``val`` or ``test``) columns. Or an NPZ with ``image``
  (strings), ``rotation`` ``(N, 3, 3)`` or ``quaternion_wxyz`` / ``quaternion_xyzw`` ``(N, 4)``, optional
  ``class`` and ``split`` (strings), and optional ``equivalent`` ``(N, M, 3, 3)``: every rotation that gives
  the same image, NaN-padded, element 0 each image's label.
* Near-unit quaternions and near-orthonormal matrices (within :data:`NEAR`) are normalised, with one log
  line that counts them; anything further off is refused, naming the file and row.
* Symmetric objects: a group name (``C<n>``, ``D<n>``, ``T``, ``O``, ``I``; :func:`image2sphere.so3.groups.
  rotation_group`) for the whole set or per class. Symmetries act on the right, as SYMSOL's: the
  equivalent rotations of ``R`` are ``R @ S`` for every ``S`` of the group (``R`` first).
"""

from __future__ import annotations

import csv
import logging
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import torch

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.data.common import CorruptImageError, check_corrupt_policy, load_image, normalize_images, skip_corrupt
from image2sphere.data.loading import EpochDataset, EpochIndex
from image2sphere.data.symsol import LABEL_MODES, rotation_fields
from image2sphere.so3.groups import rotation_group

__all__ = ["SPLITS", "FolderDataset", "FolderLabels", "equivalent_sets", "read_labels", "symmetry_groups"]

log = logging.getLogger(__name__)

SPLITS = ("train", "val", "test")
#: how far a quaternion's norm from 1, or ``max |R^T R - I|`` from 0, may be and still be normalised
NEAR = 1e-2
_QUATERNION_COLUMNS = {("qw", "qx", "qy", "qz"): "wxyz", ("qx", "qy", "qz", "qw"): "xyzw"}
_MATRIX_COLUMNS = tuple(f"r{i}{j}" for i in range(3) for j in range(3))


@dataclass
class FolderLabels:
    """What a labels file says, one entry per image (``N`` images).

    ``paths`` (relative to the folder), ``rotations`` float32 ``(N, 3, 3)``, ``classes`` (a name per image,
    ``None`` without a class column), ``splits`` (``train``/``val``/``test`` per image, ``None`` without a
    split column) and ``equivalent`` float32 ``(N, M, 3, 3)`` NaN-padded (``None``: one rotation per image
    unless a symmetry group is given). ``first_row``: how the file counts image 0 in messages (a CSV's line 2,
    below its header; an NPZ's index 0)."""

    paths: list[str]
    rotations: np.ndarray
    classes: list[str] | None
    splits: list[str] | None
    equivalent: np.ndarray | None = None
    first_row: int = 0

    def row(self, i: int) -> int:
        """Image ``i``'s row as the file counts it (what messages name)."""
        return i + self.first_row


#: a CSV's first image is on line 2, below the header
CSV_FIRST_ROW = 2


def _rows_error(source: Path, row: int | str, message: str) -> ConfigError:
    return ConfigError(f"{source}, row {row}: {message}")


def _proper(R: np.ndarray, source: Path, rows: Sequence[int | str]) -> tuple[np.ndarray, int]:
    """``R (N, 3, 3)`` float64 as proper rotations: near-orthonormal ones projected onto SO(3) (their count
    returned), others refused naming the first offending row."""
    error = np.abs(np.einsum("nji,njk->nik", R, R) - np.eye(3)).reshape(len(R), 9).max(axis=1)
    det = np.linalg.det(R)
    bad = np.flatnonzero(~np.isfinite(error) | (error > NEAR) | (det < 0))
    if len(bad):
        i = int(bad[0])
        why = (
            "has determinant -1 (a reflection)"
            if det[i] < 0
            else f"is not a rotation (max |R^T R - I| = {error[i]:.3g})"
        )
        raise _rows_error(source, rows[i], f"the matrix {why}; give a proper rotation, x_camera = R @ x_object")
    near = int(((error > 1e-6) | (np.abs(det - 1) > 1e-6)).sum())
    U, _, Vt = np.linalg.svd(R)
    return U @ Vt, near  # the nearest rotation (det +1: reflections were refused above)


def _from_quaternions(q: np.ndarray, order: str, source: Path, rows: Sequence[int | str]) -> tuple[np.ndarray, int]:
    from image2sphere.so3.rotations import quaternion_to_matrix

    norm = np.linalg.norm(q, axis=1)
    bad = np.flatnonzero(~np.isfinite(norm) | (np.abs(norm - 1) > NEAR))
    if len(bad):
        i = int(bad[0])
        raise _rows_error(source, rows[i], f"the quaternion has norm {norm[i]:.4g}, not 1 (within {NEAR:g})")
    near = int((np.abs(norm - 1) > 1e-6).sum())
    R = quaternion_to_matrix(torch.from_numpy(q / norm[:, None]), order).numpy()  # [N, 3, 3]
    return R, near


def _read_csv(source: Path) -> FolderLabels:
    try:
        with open(source, newline="") as f:
            table = list(csv.reader(f))
    except (OSError, UnicodeDecodeError, csv.Error) as e:
        raise ConfigError(f"{source} cannot be read as CSV: {e}") from None
    if not table:
        raise ConfigError(f"{source} is empty: it needs a header and a row per image")
    header = [h.strip() for h in table[0]]
    if "image" not in header:
        raise ConfigError(f"{source}: the header {header} has no 'image' column")
    columns = {name: k for k, name in enumerate(header)}
    quaternion = tuple(h for h in header if h in ("qw", "qx", "qy", "qz"))  # in the header's order
    rotation_columns = [quaternion] if quaternion in _QUATERNION_COLUMNS else []
    matrix = set(_MATRIX_COLUMNS) <= set(header)
    if len(rotation_columns) + matrix != 1 or (quaternion and not rotation_columns):
        raise ConfigError(
            f"{source}: the header must name one rotation, as qw,qx,qy,qz or qx,qy,qz,qw (a unit quaternion in "
            f"that order) or r00,r01,...,r22 (the matrix row by row); it has {header}"
        )
    names = list(rotation_columns[0]) if rotation_columns else list(_MATRIX_COLUMNS)
    rows = table[1:]
    if not rows:
        raise ConfigError(f"{source} has a header but no rows")
    numbers = np.empty((len(rows), len(names)))
    paths, classes, splits = [], [], []
    for n, row in enumerate(rows, start=CSV_FIRST_ROW):
        if len(row) != len(header):
            raise _rows_error(source, n, f"{len(row)} fields, the header has {len(header)}")
        paths.append(row[columns["image"]].strip())
        try:
            numbers[n - CSV_FIRST_ROW] = [float(row[columns[c]]) for c in names]
        except ValueError:
            raise _rows_error(source, n, f"the rotation {[row[columns[c]] for c in names]} is not numbers") from None
        if "class" in columns:
            classes.append(row[columns["class"]].strip())
        if "split" in columns:
            splits.append(row[columns["split"]].strip())
    line_numbers = list(range(CSV_FIRST_ROW, len(rows) + CSV_FIRST_ROW))
    if rotation_columns:
        R, near = _from_quaternions(numbers, _QUATERNION_COLUMNS[rotation_columns[0]], source, line_numbers)
    else:
        R, near = _proper(numbers.reshape(-1, 3, 3), source, line_numbers)
    if near:
        log.info("%s: %d of %d rotations were not exactly unit or orthonormal and were normalised", source, near,
                 len(R))  # fmt: skip
    return FolderLabels(paths, R.astype(np.float32), classes if "class" in columns else None,
                        splits if "split" in columns else None, first_row=CSV_FIRST_ROW)  # fmt: skip


def _read_npz(source: Path) -> FolderLabels:
    try:
        with np.load(source, allow_pickle=False) as z:
            arrays = {k: z[k] for k in z.files}
    except (OSError, ValueError, EOFError) as e:
        raise ConfigError(f"{source} cannot be read as NPZ (without pickles): {e}") from None
    if "image" not in arrays:
        raise ConfigError(f"{source} has no 'image' array (it has {sorted(arrays)})")
    paths = [str(p) for p in arrays["image"].reshape(-1)]
    n = len(paths)
    given = [k for k in ("rotation", "quaternion_wxyz", "quaternion_xyzw") if k in arrays]
    if len(given) != 1:
        raise ConfigError(f"{source} must hold one of rotation, quaternion_wxyz, quaternion_xyzw; it has {given}")
    values = np.asarray(arrays[given[0]], dtype=np.float64)
    want = (n, 3, 3) if given[0] == "rotation" else (n, 4)
    if values.shape != want:
        raise ConfigError(f"{source}: {given[0]} has shape {values.shape}; {n} images need {want}")
    rows = list(range(n))
    if given[0] == "rotation":
        R, near = _proper(values, source, rows)
    else:
        R, near = _from_quaternions(values, given[0][-4:], source, rows)
    if near:
        log.info("%s: %d of %d rotations were normalised", source, near, n)
    optional = {}
    for key in ("class", "split"):
        if key in arrays:
            if arrays[key].shape != (n,):
                raise ConfigError(f"{source}: {key} has shape {arrays[key].shape}; {n} images need ({n},)")
            optional[key] = [str(v) for v in arrays[key]]
    equivalent = None
    if "equivalent" in arrays:
        equivalent = np.asarray(arrays["equivalent"], dtype=np.float64)
        if equivalent.ndim != 4 or equivalent.shape[0] != n or equivalent.shape[2:] != (3, 3):
            raise ConfigError(f"{source}: equivalent has shape {equivalent.shape}; {n} images need ({n}, M, 3, 3)")
        real = ~np.isnan(equivalent).any(axis=(2, 3))  # [N, M]
        if not real[:, 0].all() or (real[:, 1:] & ~real[:, :-1]).any():
            i = int(np.flatnonzero(~real[:, 0] | (real[:, 1:] & ~real[:, :-1]).any(axis=1))[0])
            raise _rows_error(source, i, "equivalent: the row's rotations first, then the NaN padding")
        flat = np.where(real[..., None, None], equivalent, np.eye(3)).reshape(-1, 3, 3)
        projected, _ = _proper(flat, source, [i // equivalent.shape[1] for i in range(len(flat))])
        equivalent = np.where(real[..., None, None], projected.reshape(equivalent.shape), np.nan)
        off = np.abs(equivalent[:, 0] - R).reshape(n, 9).max(axis=1)
        if (off > 1e-3).any():
            i = int(np.argmax(off))
            raise _rows_error(source, i, "equivalent[row, 0] is not the row's rotation")
        equivalent = equivalent.astype(np.float32)
    return FolderLabels(paths, R.astype(np.float32), optional.get("class"), optional.get("split"), equivalent)


def read_labels(source: str | Path) -> FolderLabels:
    """The labels file ``source`` (``.csv`` or ``.npz``; module docstring), checked: a :class:`ConfigError`
    naming the file and row for anything it refuses."""
    source = Path(source)
    if not source.is_file():
        raise InputNotFoundError(f"the labels file {source} does not exist (dataset.labels, relative to dataset.root)")
    if source.suffix.lower() == ".csv":
        labels = _read_csv(source)
    elif source.suffix.lower() == ".npz":
        labels = _read_npz(source)
    else:
        raise ConfigError(f"dataset.labels={source.name}: a .csv or .npz file")
    if labels.splits is not None:
        unknown = sorted(set(labels.splits) - set(SPLITS))
        if unknown:
            row = labels.row(labels.splits.index(unknown[0]))
            raise _rows_error(source, row, f"split {unknown[0]!r} is none of {', '.join(SPLITS)}")
    return labels


def symmetry_groups(
    symmetry: str | Mapping[str, str] | None, class_names: Sequence[str], from_file: bool = False
) -> dict[str, torch.Tensor] | None:
    """The symmetry group of each class, float32 ``(G, 3, 3)`` identity first, from ``dataset.symmetry``: one
    group name for every class, a group per class name, or ``None`` (no symmetry). ``from_file``: the labels
    file gives every image's equivalent rotations itself (then ``symmetry`` must be ``None``)."""
    if symmetry is None:
        return None
    if from_file:
        raise ConfigError("dataset.symmetry must be null when the labels file gives its equivalent rotations")
    per_class = dict(symmetry) if isinstance(symmetry, Mapping) else {name: symmetry for name in class_names}
    unknown = sorted(set(per_class) - set(class_names))
    if unknown:
        raise ConfigError(f"dataset.symmetry names classes {unknown} that the labels do not have ({list(class_names)})")
    groups = {}
    for name, group in per_class.items():
        try:
            groups[name] = rotation_group(str(group)).to(torch.float32)
        except ConfigError:
            raise ConfigError(
                f"dataset.symmetry: {group!r} (for {name!r}) is not a group: C<n>, D<n> (n >= 1), T, O or I"
            ) from None
    return groups


def image_classes(labels: FolderLabels, class_names: Sequence[str]) -> list[str]:
    """Each image's class name: the labels' class column, or the one class of a file without it."""
    return labels.classes if labels.classes is not None else [class_names[0]] * len(labels.paths)


def equivalent_sets(
    labels: FolderLabels, groups: Mapping[str, torch.Tensor] | None, class_names: Sequence[str]
) -> tuple[torch.Tensor, torch.Tensor]:
    """Every image's equivalent rotations ``(N, M, 3, 3)`` (padded with the label) and their counts ``(N,)``:
    the NPZ's ``equivalent``, else ``R @ S`` for every ``S`` of the group of the image's class
    (:func:`symmetry_groups`), else the label alone."""
    R = torch.from_numpy(labels.rotations)
    if labels.equivalent is not None:
        sets = torch.from_numpy(labels.equivalent)  # [N, M, 3, 3], NaN padding last (checked when read)
        real = ~torch.isnan(sets).any(dim=(2, 3))  # [N, M]
        return torch.where(real[..., None, None], sets, R[:, None]), real.sum(1)
    if not groups:
        return R[:, None].clone(), torch.ones(len(R), dtype=torch.long)
    largest = max(len(g) for g in groups.values())
    names = image_classes(labels, class_names)
    sets = R[:, None].expand(len(R), largest, 3, 3).clone()
    counts = torch.ones(len(R), dtype=torch.long)
    for i, name in enumerate(names):
        if name in groups:
            g = groups[name]
            sets[i, : len(g)] = R[i] @ g  # [G, 3, 3], R first (the identity is element 0)
            counts[i] = len(g)
    return sets, counts


class FolderDataset(EpochDataset):
    """Images of a folder with their rotations: the items of :class:`~image2sphere.data.symsol.SymsolDataset`
    (``image``, ``class_index``, ``index``, and ``rotation`` or ``rotations`` with ``mask``).

    Args:
        root: the folder the image paths are relative to.
        paths: each image's path.
        sets, counts: each image's equivalent rotations ``(N, M, 3, 3)`` (element 0 its label) and their count.
        class_index: each image's class ``(N,)``.
        rows: the images of this split (indices into the above).
        label, return_all, image_size, seed, on_corrupt: as :class:`~image2sphere.data.symsol.SymsolDataset`'s.
    """

    def __init__(self, root: str | Path, paths: Sequence[str], sets: torch.Tensor, counts: torch.Tensor,
                 class_index: torch.Tensor, rows: np.ndarray, label: str = "random", return_all: bool = False,
                 image_size: int = 224, seed: int = 0, on_corrupt: str = "fail"):  # fmt: skip
        if label not in LABEL_MODES:
            raise ConfigError(f"dataset.label must be one of {LABEL_MODES}, got {label!r}")
        self.root, self.paths = Path(root), list(paths)
        self.sets, self.counts, self.class_index = sets, counts, class_index
        self.rows = np.asarray(rows, dtype=np.int64)
        self.label, self.return_all = label, bool(return_all)
        self.image_size, self.seed = int(image_size), int(seed)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        self.max_m = int(counts[self.rows].max()) if len(self.rows) else 1
        self._warned: set[str] = set()

    def __len__(self) -> int:
        return len(self.rows)

    def __getitem__(self, key: int | EpochIndex) -> dict[str, torch.Tensor] | None:
        epoch, i = self.epoch_and_index(key)
        row = int(self.rows[i])
        try:
            image = load_image(self.root / self.paths[row], self.image_size)
        except CorruptImageError as e:
            skip_corrupt(e, self.on_corrupt, self._warned)
            return None
        c = int(self.class_index[row])
        item = {"image": normalize_images(image), "class_index": torch.tensor(c), "index": torch.tensor(row)}
        seed = (self.seed, epoch, c, row)
        item.update(rotation_fields(self.sets[row], int(self.counts[row]), self.max_m, self.label, self.return_all,
                                    seed))  # fmt: skip
        return item


# ------------------------------------------------------------------------------------------ the convention check
def axes_in_image(R: np.ndarray, size: float) -> np.ndarray:
    """Where the object's x, y and z axes point in an image of ``size`` pixels under ``R`` (``x_camera =
    R @ x_object``, camera x to the right of the image, y up, z toward the viewer): ``(3, 3)``, row ``k`` the
    pixel offset (column, row) of axis ``k``'s tip from the image centre at length ``0.4 size``, then its
    camera z (> 0: toward the viewer)."""
    length = 0.4 * size
    axes = np.asarray(R, dtype=np.float64).T  # row k: column k of R, axis k in camera coordinates
    return np.stack([length * axes[:, 0], -length * axes[:, 1], axes[:, 2]], axis=1)  # image rows run down


def draw_label_axes(root: str | Path, labels: str = "labels.csv", images: int = 6, out: str | Path | None = None,
                    ) -> Path:  # fmt: skip
    """The first ``images`` images of a folder with their labels' object axes drawn on them (x red, y green,
    z blue; solid toward the viewer, dashed away), into ``out`` (default ``<root>/<labels>_axes.png``; never
    overwritten). Returns the file written."""
    from matplotlib.figure import Figure

    from image2sphere.plot import figure_format, save_figure

    root = Path(root)
    table = read_labels(root / labels)
    out = Path(out) if out is not None else root / f"{Path(labels).stem}_axes.png"
    figure_format(out, "--out")
    n = min(int(images), len(table.paths))
    fig = Figure(figsize=(2.4 * n, 2.6))
    for i in range(n):
        ax = fig.add_subplot(1, n, i + 1)
        image = load_image(root / table.paths[i]).numpy()
        h, w = image.shape[:2]
        ax.imshow(image)
        for (dx, dy, toward), colour, name in zip(axes_in_image(table.rotations[i], min(h, w)), "rgb", "xyz",
                                                  strict=True):  # fmt: skip
            style = "-" if toward >= 0 else "--"
            ax.plot([w / 2, w / 2 + dx], [h / 2, h / 2 + dy], style, color=colour, linewidth=2)
            ax.annotate(name, (w / 2 + 1.1 * dx, h / 2 + 1.1 * dy), color=colour, ha="center", va="center")
        ax.set_title(Path(table.paths[i]).name, fontsize=8)
        ax.set_axis_off()
    return save_figure(fig, out)


def main(argv: list[str] | None = None) -> int:
    import argparse
    import sys

    from image2sphere.checks import Refusal

    parser = argparse.ArgumentParser(
        prog="python -m image2sphere.data.folder",
        description="Draw the labels' object axes on the first images of a folder (dataset=folder), to see "
        "before training whether the rotations mean x_camera = R @ x_object (camera x right, y up, z toward you).",
    )
    parser.add_argument("root", help="the folder (dataset.root)")
    parser.add_argument("--labels", default="labels.csv", help="the labels file, relative to the folder")
    parser.add_argument("--images", type=int, default=6, help="how many images (the first of the file)")
    parser.add_argument("--out", default=None, help="the picture to write (default <root>/<labels>_axes.png)")
    args = parser.parse_args(argv)
    try:
        path = draw_label_axes(args.root, args.labels, args.images, args.out)
    except Refusal as e:
        print(f"Error: {e}", file=sys.stderr)
        return 1
    print(f"wrote {path}: x red, y green, z blue; solid toward the viewer, dashed away")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
