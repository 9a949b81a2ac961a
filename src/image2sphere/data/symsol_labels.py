"""SYMSOL's label files in their published layout (that of ``symsol_dataset.zip``): ``rotations.npz``,
read and checked by :func:`load_symsol_rotations`. The images are read by :mod:`image2sphere.data.symsol`.

Layout (docs/datasets.md#symsol-layout)
---------------------------------------
``{root}/{train,test}/images/{shape}_{i:05d}.png`` and ``{root}/{split}/rotations.npz`` with one
key per shape, each ``(N, M, 3, 3)``: the rotations equivalent under the shape's symmetry for every
image, ``[:, 0]`` the rendering rotation. Where ``M`` varies between images (marked shapes of
SYMSOL II) the array is either an object array of ``(M_i, 3, 3)`` arrays or padded to the largest
``M``; padding entries are matrices that are all NaN (what :mod:`image2sphere.data.render` writes)
or all zero. Both are accepted; :func:`load_symsol_rotations` reports which one it found. Object
arrays are unpickled with :class:`image2sphere.data.safe_io.RestrictedUnpickler` (numpy arrays only,
never code), and every real entry is checked to be a finite rotation when the file is loaded.
"""

from __future__ import annotations

import logging
from collections.abc import Sequence
from pathlib import Path

import numpy as np

from image2sphere.checks import ConfigError, InputNotFoundError
from image2sphere.data.safe_io import load_npz, npz_keys
from image2sphere.data.shapes import SYMSOL_II_SHAPES

__all__ = ["ORTHONORMAL_ATOL", "SYMSOL_DOCS", "SYMSOL_URL", "load_symsol_rotations"]

log = logging.getLogger(__name__)

ORTHONORMAL_ATOL = 1e-3
SYMSOL_DOCS = "docs/datasets.md#symsol-layout"
SYMSOL_URL = (
    "https://storage.googleapis.com/gresearch/implicit-pdf/symsol_dataset.zip "
    "(linked from github.com/google-research/google-research/tree/master/implicit_pdf)"
)


def _padding_rows(a: np.ndarray) -> np.ndarray:
    """``(N, M)`` True where a matrix of ``(N, M, 3, 3)`` is padding (all NaN or all zero)."""
    flat = a.reshape(*a.shape[:2], 9)
    return np.isnan(flat).all(-1) | (flat == 0).all(-1)


def _dense_from_object(path: Path, shape: str, a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``(dense (N, M_max, 3, 3) float32, real (N, M_max))`` of an object array of ``(M_i, 3, 3)`` arrays."""
    if a.ndim != 1:
        raise ConfigError(
            f"{path}[{shape!r}]: an object array must be 1-D (one (M_i, 3, 3) array per image), got shape {a.shape} "
            f"(see {SYMSOL_DOCS})"
        )
    rows = []
    for i, r in enumerate(a):
        try:
            r = np.asarray(r, dtype=np.float32)
        except (TypeError, ValueError):
            raise ConfigError(
                f"{path}[{shape!r}]: image {i} holds a {type(r).__name__}, not an (M, 3, 3) array of numbers"
            ) from None
        if r.shape == (3, 3):
            r = r[None]
        if r.ndim != 3 or r.shape[1:] != (3, 3):
            raise ConfigError(f"{path}[{shape!r}]: image {i} holds an array of shape {r.shape}, expected (M, 3, 3)")
        rows.append(r)
    counts = np.array([len(r) for r in rows], dtype=np.int64)
    dense = np.zeros((len(rows), max(counts, default=1), 3, 3), np.float32)
    for i, r in enumerate(rows):
        dense[i, : len(r)] = r
    return dense, np.arange(dense.shape[1])[None, :] < counts[:, None]


def _rotation_problems(dense: np.ndarray, real: np.ndarray, chunk: int = 1 << 18) -> tuple[np.ndarray, np.ndarray]:
    """Check every real matrix of ``dense (N, M, 3, 3)`` (``real (N, M)``): ``(bad (N, M) bool, code (N, M))``
    with ``code`` 1 for NaN/inf entries, 2 for not orthonormal (an entry of ``R R^T - I`` above 1e-3),
    3 for ``det != 1`` (a reflection). Written out entry by entry (fast for tens of millions of
    matrices) on blocks of about ``chunk`` matrices."""
    n, m = real.shape
    code = np.zeros((n, m), dtype=np.int8)
    rows = max(1, chunk // max(m, 1))
    for start in range(0, n, rows):
        block = dense[start : start + rows].reshape(-1, 3, 3)
        finite = np.isfinite(block).all(axis=(-1, -2))
        r0, r1, r2 = (np.where(finite[:, None], block[:, k], 0.0) for k in range(3))  # the rows, [K, 3]
        err = np.max(
            np.abs(
                [
                    np.einsum("ki,ki->k", r0, r0) - 1,
                    np.einsum("ki,ki->k", r1, r1) - 1,
                    np.einsum("ki,ki->k", r2, r2) - 1,
                    np.einsum("ki,ki->k", r0, r1),
                    np.einsum("ki,ki->k", r0, r2),
                    np.einsum("ki,ki->k", r1, r2),
                ]
            ),
            axis=0,
        )
        cross = np.stack(
            [r1[:, 1] * r2[:, 2] - r1[:, 2] * r2[:, 1], r1[:, 2] * r2[:, 0] - r1[:, 0] * r2[:, 2],
             r1[:, 0] * r2[:, 1] - r1[:, 1] * r2[:, 0]], axis=1,
        )  # fmt: skip
        det = np.einsum("ki,ki->k", r0, cross)
        c = np.select([~finite, err > ORTHONORMAL_ATOL, np.abs(det - 1) > ORTHONORMAL_ATOL], [1, 2, 3], 0)
        c = c.reshape(-1, m)
        code[start : start + rows] = np.where(real[start : start + rows], c, 0)
    return code > 0, code


def _check_rotations(path: Path, shape: str, dense: np.ndarray, real: np.ndarray) -> None:
    """``ValueError`` naming the file, key, image and entry when a real matrix is not a rotation."""
    bad, code = _rotation_problems(dense, real)
    if not bad.any():
        return
    rows = np.flatnonzero(bad.any(1))
    details = []
    for i in rows[:3]:
        j = int(np.flatnonzero(bad[i])[0])
        R = dense[i, j].astype(np.float64)
        if code[i, j] == 1:
            what = "holds NaN or inf"
        elif code[i, j] == 2:
            what = f"is not orthonormal (largest entry of |R R^T - I| is {np.abs(R @ R.T - np.eye(3)).max():.3g})"
        else:
            what = f"has determinant {np.linalg.det(R):.3g} (a reflection, not a rotation)"
        details.append(f"image {i} (images/{shape}_{i:05d}.png), equivalent rotation {j} {what}")
    raise ConfigError(
        f"{path}[{shape!r}]: rows {rows[:5].tolist()} are not rotation matrices (R R^T != I, det != 1 or not "
        f"finite): {'; '.join(details)} ({int(bad.sum())} bad matrices in {len(rows)} images). The file is "
        f"corrupt: re-download {SYMSOL_URL} or re-render the set"
    )


def load_symsol_rotations(split_dir: str | Path, shapes: Sequence[str]) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Read ``{split_dir}/rotations.npz``: per shape ``(rotations (N, M, 3, 3) float32, counts (N,))``.

    Rows are compacted so that the first ``counts[i]`` entries of row ``i`` are real; the rest is
    padding filled with the row's first rotation. Object arrays are read without running pickled code
    (:func:`image2sphere.data.safe_io.load_npz`). Raises a ``ValueError`` naming the file and key when
    the archive is truncated or corrupt, a shape is missing, an array has the wrong shape or type, an
    unmarked shape has padding, or any real entry (every equivalent rotation, not only ``[:, 0]``) is
    not a finite rotation matrix (then also naming the image and entry).
    """
    path = Path(split_dir) / "rotations.npz"
    if not path.is_file():
        raise InputNotFoundError(
            f"SYMSOL rotations not found: {path} (expected {{split}}/rotations.npz next to {{split}}/images/; "
            f"see {SYMSOL_DOCS})"
        )
    remedy = f"re-download {SYMSOL_URL} and unzip it again (or re-render the set)"
    keys = npz_keys(path, remedy)
    for shape in shapes:
        if shape not in keys:
            raise ConfigError(
                f"{path} has no key {shape!r} (keys: {sorted(keys)}; expected one key per shape, see {SYMSOL_DOCS})"
            )
    arrays = load_npz(path, list(dict.fromkeys(shapes)), remedy)
    out = {}
    for shape in shapes:
        a = arrays[shape]
        if a.dtype == object:
            dense, real = _dense_from_object(path, shape, a)
            kind = "object array"
        else:
            if a.ndim != 4 or a.shape[-2:] != (3, 3):
                raise ConfigError(f"{path}[{shape!r}] must have shape (N, M, 3, 3), got {a.shape} (see {SYMSOL_DOCS})")
            if a.dtype.kind not in "fiu":
                raise ConfigError(f"{path}[{shape!r}] must hold numbers (float), got dtype {a.dtype}")
            dense = a.astype(np.float32, copy=True)
            real = ~_padding_rows(dense)
            kind = "dense" if real.all() else "padded"
        counts = real.sum(1)
        if len(dense) == 0:
            raise ConfigError(f"{path}[{shape!r}] holds no images")
        if (counts < 1).any():
            raise ConfigError(f"{path}[{shape!r}]: rows {np.flatnonzero(counts < 1)[:5].tolist()} have no rotation")
        if shape not in SYMSOL_II_SHAPES and (counts != counts.max()).any():
            short = np.flatnonzero(counts != counts.max())
            raise ConfigError(
                f"{path}[{shape!r}]: rows {short[:5].tolist()} have fewer equivalent rotations ({counts[short[0]]}) "
                f"than the others ({counts.max()}): their missing entries are all NaN or all zero, but {shape!r} is "
                f"unmarked and has the same symmetry group in every image. The file is corrupt: re-download "
                f"{SYMSOL_URL} or re-render the set"
            )
        _check_rotations(path, shape, dense, real)
        if kind == "padded":
            order = np.argsort(~real, axis=1, kind="stable")  # real entries first, in order
            dense = np.take_along_axis(dense, order[..., None, None], axis=1)
        m = np.arange(dense.shape[1])
        dense = np.where((m[None, :] < counts[:, None])[..., None, None], dense, dense[:, :1])
        log.info("%s[%s]: %d images, M %d..%d (%s)", path, shape, len(dense), counts.min(), counts.max(), kind)
        out[shape] = (dense, counts)
    return out
