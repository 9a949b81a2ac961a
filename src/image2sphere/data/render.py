"""Vectorised ray-casting renderer of the SYMSOL shapes, and a writer of the published SYMSOL layout.

Conventions
-----------
* Rotation matrices ``(..., 3, 3)``, column vectors, ``x_camera = R @ x_object`` (docs/conventions.md);
  shapes, object frame and units as in :mod:`image2sphere.data.shapes`.
* Camera: orthographic; camera frame ``x`` right, ``y`` up, ``z`` toward the viewer; rays travel along
  ``-z``. The image covers ``[-1, 1]^2`` of the camera ``x-y`` plane; image row 0 is the top
  (``y = +1``), column 0 the left (``x = -1``). Pixel ``(i, j)`` of an ``S x S`` image is the box
  ``x in [-1 + 2j/S, -1 + 2(j+1)/S]``, ``y in [1 - 2(i+1)/S, 1 - 2i/S]``; it is sampled at the
  centres of a ``supersample x supersample`` sub-grid and the samples are averaged (box filter).
* The ray through ``(x, y)`` is ``p(s) = (x, y, -s)`` in the camera frame (``s`` grows away from the
  viewer); in the object frame it is ``R^T p(s)``. Each convex constraint of the solid
  (``n . x_obj <= h``: ``(R n) . p(s) <= h``; a quadric ``q(R^T p(s)) <= 0``) gives an interval of
  ``s``, solved analytically; the ray hits where ``max s_in <= min s_out`` and the visible point and its
  normal are those of the constraint that gives ``max s_in``.
* Shading (all in the camera frame): ``albedo * (AMBIENT + DIFFUSE * max(0, n . LIGHT_DIRECTION))``;
  black background. It depends on camera-frame normals only, so ``R`` and ``R @ S`` for a symmetry
  ``S`` give the same image up to float error.
* Images are ``torch.uint8`` ``(..., H, W, 3)`` RGB.

SYMSOL layout written by :func:`render_symsol` (docs/datasets.md#symsol-layout, docs/renderer.md)
--------------------------------------------------------------------------------------------------
``root/{split}/images/{shape}_{i:05d}.png`` (RGB, ``i`` 0-based per shape = row of the npz) and
``root/{split}/rotations.npz``: one key per shape, float32 ``(N, M, 3, 3)``, ``[:, 0]`` the rendering
rotation. For marked shapes ``M`` varies between images; the arrays are NaN-padded to the largest ``M``
of the split (readers treat all-NaN matrices as padding). ``root/render_info.json`` records the
parameters.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import math
import os
import shutil
import sys
import time
import zipfile
from collections.abc import Sequence
from concurrent.futures import Future, ThreadPoolExecutor
from pathlib import Path
from typing import NamedTuple

import numpy as np
import torch

from image2sphere.data.shapes import (
    CONE_APEX_HEIGHT,
    CONE_BASE_DEPTH,
    CONE_BASE_RADIUS,
    CYL_HALF_HEIGHT,
    CYL_RADIUS,
    SHAPES,
    SPHERE_RADIUS,
    ShapeGeometry,
    check_shape,
    check_shape_list,
    exact_matmul3,
    shape_geometry,
)
from image2sphere.data.symmetry import equivalent_rotation_sets
from image2sphere.data.workers import available_cpus
from image2sphere.so3.rotations import check_rotation_matrix, random_rotations

__all__ = [
    "AMBIENT",
    "DIFFUSE",
    "FORMAT_VERSION",
    "LABEL_BACKGROUND",
    "LABEL_BODY",
    "LABEL_MARK_DISC",
    "LABEL_MARK_DOT",
    "LIGHT_DIRECTION",
    "RayHits",
    "cast_rays",
    "main",
    "render",
    "render_symsol",
    "symsol_rotations",
]

log = logging.getLogger(__name__)

LIGHT_DIRECTION = tuple(v / math.sqrt(0.3**2 + 0.5**2 + 1.0) for v in (-0.3, 0.5, 1.0))  # camera frame, unit
AMBIENT = 0.3
DIFFUSE = 0.7

LABEL_BACKGROUND, LABEL_BODY, LABEL_MARK_DISC, LABEL_MARK_DOT = 0, 1, 2, 3

FORMAT_VERSION = 1
# Bump whenever the geometry, colours, shading or sampling change: a cached set rendered by another version
# then no longer matches, and render_symsol refuses it (delete it to render it again).
RENDERER_VERSION = 1

_BIG = 1e30  # stands for an infinite ray parameter
_TINY = 1e-12  # |n_z| below this counts as edge-on
_CHUNK_SAMPLES = 1 << 18  # rays per chunk: keeps the working set of each pass in cache (~1 MB per buffer)


# --------------------------------------------------------------------------------------------------
# Ray casting
# --------------------------------------------------------------------------------------------------


def _axis_coords(n: int, dtype: torch.dtype) -> torch.Tensor:
    """Centres ``(n,)`` of ``n`` equal cells over ``[-1, 1]``, ascending (camera ``x`` of the columns)."""
    return ((torch.arange(n, dtype=torch.float64) + 0.5) * (2.0 / n) - 1.0).to(dtype)


def _rotate(R: torch.Tensor, v: torch.Tensor) -> torch.Tensor:
    """``R @ v`` for ``R`` ``(B, 3, 3)`` and vectors ``v`` ``(K, 3)``: ``(B, K, 3)``, explicit sums."""
    return (
        R[:, None, :, 0] * v[None, :, 0, None]
        + R[:, None, :, 1] * v[None, :, 1, None]
        + R[:, None, :, 2] * v[None, :, 2, None]
    )


def _support(geom: ShapeGeometry, u: torch.Tensor) -> torch.Tensor:
    """Support function ``max_{x in solid} u . x`` for object-frame unit vectors ``u`` ``(..., 3)``."""
    if geom.vertices is not None:
        return (u[..., None, :] * geom.vertices.to(u.dtype)).sum(-1).amax(-1)
    kind = geom.quadric.kind
    if kind == "sphere":
        return torch.full(u.shape[:-1], SPHERE_RADIUS, dtype=u.dtype)
    along = u[..., 1]  # the axis is y
    across = torch.sqrt((1 - along * along).clamp_min(0.0))
    if kind == "cylinder":
        return CYL_HALF_HEIGHT * along.abs() + CYL_RADIUS * across
    return torch.maximum(CONE_APEX_HEIGHT * along, -CONE_BASE_DEPTH * along + CONE_BASE_RADIUS * across)


def _pixel_window(geom: ShapeGeometry, R: torch.Tensor, size: int) -> tuple[int, int, int, int]:
    """Rows ``[i0, i1)`` and columns ``[j0, j1)`` of a ``size x size`` image that can show the shape.

    The union over the batch ``R`` ``(B, 3, 3)`` of the pixels meeting the projection's bounding box
    (camera ``x`` extent ``[-h(-r0), h(r0)]`` with ``h`` the support function and ``r0`` the first row
    of ``R``; likewise ``y``). Pixels outside the window are background.
    """
    R64 = R.to(torch.float64)
    rows = torch.cat([R64[:, :2], -R64[:, :2]], dim=1)  # [B, 4, 3]: +x, +y, -x, -y in the object frame
    h = _support(geom, rows).amax(0) + 1e-6  # [4]
    x_lo, y_lo, x_hi, y_hi = -float(h[2]), -float(h[3]), float(h[0]), float(h[1])

    def cells(lo: float, hi: float) -> tuple[int, int]:
        a = min(max(math.floor((lo + 1.0) * size / 2.0), 0), size)
        b = min(max(math.floor((hi + 1.0) * size / 2.0) + 1, 0), size)
        return a, max(a, b)

    j0, j1 = cells(x_lo, x_hi)
    i0, i1 = cells(-y_hi, -y_lo)  # row i covers y in [1 - 2 (i + 1) / S, 1 - 2 i / S]
    return i0, i1, j0, j1


def _cast(
    geom: ShapeGeometry, R: torch.Tensor, xs: torch.Tensor, ys: torch.Tensor, normals: bool = False
) -> dict[str, torch.Tensor]:
    """Cast the rays of the grid ``(ys[i], xs[j])`` at rotations ``R`` ``(B, 3, 3)`` (all one dtype).

    Returns ``hit`` bool, ``s`` (the ray parameter of the visible point, 0 where missed), ``shade`` (the
    Lambertian factor, 0 where missed) and ``label`` uint8, each ``(B, len(ys), len(xs))``, and with
    ``normals`` also ``normal`` ``(B, len(ys), len(xs), 3)`` (camera frame, 0 where missed).

    Planes: along ``p(s) = (x, y, -s)``, ``m . p <= h`` (``m = R n``) reads ``s >= sigma`` if ``m_z > 0``
    (the face looks at the camera) and ``s <= sigma`` if ``m_z < 0``, with ``sigma = (m_x x + m_y y - h)
    / m_z``. A plane with ``|m_z| < tiny`` (edge-on) is treated as ``m_z = +tiny``: ``sigma`` is then
    ``-huge`` inside and ``+huge`` outside, which is the right answer. Faces are sorted per image into
    front and back sets and folded one at a time into running ``max s_in`` / ``min s_out``.
    """
    B, dt = R.shape[0], R.dtype
    X = xs[None, None, :]  # [1, 1, W]
    Y = ys[None, :, None]  # [1, H, 1]
    grid = (B, ys.numel(), xs.numel())
    light = torch.tensor(LIGHT_DIRECTION, dtype=dt)
    s_in = torch.full(grid, -_BIG, dtype=dt)
    s_out = torch.full(grid, _BIG, dtype=dt)
    shade = torch.zeros(grid, dtype=dt)
    F = geom.plane_normals.shape[0]
    face = torch.zeros(grid, dtype=torch.long) if normals else None
    if F:
        m = _rotate(R, geom.plane_normals.to(dt))  # [B, F, 3] camera-frame face normals
        mz = m[..., 2]
        mz = torch.where(mz.abs() < _TINY, torch.full_like(mz, _TINY), mz)
        front = mz > 0  # [B, F]
        coef = torch.stack([m[..., 0] / mz, m[..., 1] / mz, -geom.plane_offsets.to(dt) / mz], -1)  # [B, F, 3]
        face_cos = m[..., 0] * light[0] + m[..., 1] * light[1] + m[..., 2] * light[2]  # [B, F]
        face_shade = AMBIENT + DIFFUSE * face_cos.clamp_min(0.0)
        for select, pad in ((front, -_BIG), (~front, _BIG)):
            count = int(select.sum(1).max())
            order = torch.argsort((~select).to(torch.int8), dim=1, stable=True)[:, :count]  # [B, K] selected first
            valid = torch.gather(select, 1, order)  # [B, K]
            k = torch.gather(coef, 1, order[..., None].expand(B, count, 3))
            k = torch.where(valid[..., None], k, torch.tensor([0.0, 0.0, pad], dtype=dt))  # dummy planes
            kshade = torch.gather(face_shade, 1, order)
            for i in range(count):
                ka, kb, kc = (k[:, i, j, None, None] for j in range(3))  # [B, 1, 1]
                sigma = (ka * X + kc) + kb * Y  # [B, H, W]: a column term plus a row term
                if pad < 0:
                    closer = sigma > s_in
                    s_in = torch.where(closer, sigma, s_in)
                    shade = torch.where(closer, kshade[:, i, None, None], shade)
                    if normals:
                        face = torch.where(closer, order[:, i, None, None], face)
                else:
                    torch.minimum(s_out, sigma, out=s_out)
    quad_entry = None
    if geom.quadric is not None:
        q_in, q_out, Q, bq = _quadric_interval(geom, R, X, Y)
        quad_entry = q_in > s_in
        s_in = torch.maximum(s_in, q_in)
        torch.minimum(s_out, q_out, out=s_out)
    hit = s_in <= s_out
    s = torch.where(hit, s_in, torch.zeros_like(s_in))
    if quad_entry is not None:
        # outward normal direction at p = (x, y, -s): the gradient Q p + b
        g = [Q[:, i, 0, None, None] * X + Q[:, i, 1, None, None] * Y - Q[:, i, 2, None, None] * s for i in range(3)]
        g = [gi + bq[:, i, None, None] for i, gi in enumerate(g)]
        gnorm = torch.sqrt(g[0] * g[0] + g[1] * g[1] + g[2] * g[2]).clamp_min(1e-12)
        cos = (g[0] * light[0] + g[1] * light[1] + g[2] * light[2]) / gnorm
        shade = torch.where(quad_entry, AMBIENT + DIFFUSE * cos.clamp_min(0.0), shade)
    shade = torch.where(hit, shade, torch.zeros_like(shade))
    label = hit.to(torch.uint8)
    for part in geom.marks:  # later parts (the dot) are drawn over earlier ones
        c = _rotate(R, part.centre.to(dt)[None])[:, 0]  # [B, 3] camera frame
        dx, dy = X - c[:, 0, None, None], Y - c[:, 1, None, None]
        dz = s + c[:, 2, None, None]  # -(z - c_z) with z = -s
        inside = hit & ((dx * dx + dy * dy) + dz * dz <= part.radius**2)
        label = torch.where(inside, torch.full_like(label, part.label), label)
    out = {"hit": hit, "s": s, "shade": shade, "label": label}
    if normals:
        n = torch.zeros(*grid, 3, dtype=dt)
        if F:
            n = m[torch.arange(B)[:, None], face.reshape(B, -1)].reshape(*grid, 3)
        if quad_entry is not None:
            nq = torch.stack(g, dim=-1) / gnorm[..., None]
            n = torch.where(quad_entry[..., None], nq, n)
        out["normal"] = torch.where(hit[..., None], n, torch.zeros_like(n))
    return out


def _quadric_interval(
    geom: ShapeGeometry, R: torch.Tensor, X: torch.Tensor, Y: torch.Tensor
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(s_in, s_out)`` ``(B, H, W)`` of the quadric solid along the rays, and its camera-frame ``Q``, ``b``.

    ``q(p(s)) = A s^2 + 2 Bh s + C`` with ``Q``, ``b`` rotated to the camera frame (``R Q R^T``, ``R b``).
    ``A > 0``: the solid is ``[r_lo, r_hi]`` (empty without real roots). ``A < 0`` (only the cone, for
    rays steeper than its generators): ``q <= 0`` is two half-lines on opposite nappes, and the one on
    the lower nappe is kept: ``(-inf, r_lo]`` if the ray climbs the axis, else ``[r_hi, inf)``. When
    ``A > 0`` an interval on the upper nappe is removed by the cone's apex plane. Roots use the
    cancellation-free form ``qq / A``, ``C / qq``.
    """
    quad = geom.quadric
    dt = R.dtype
    Q = exact_matmul3(exact_matmul3(R, quad.Q.to(dt)[None]), R.transpose(1, 2))  # [B, 3, 3]
    bq = _rotate(R, quad.b.to(dt)[None])[:, 0]  # [B, 3]
    q = {(i, j): Q[:, i, j, None, None] for i in range(3) for j in range(3)}
    bc = [bq[:, i, None, None] for i in range(3)]
    A = q[2, 2]  # [B, 1, 1]
    A = torch.where(A.abs() < _TINY, torch.full_like(A, _TINY), A)
    Bh = -((q[2, 0] * X + bc[2]) + q[2, 1] * Y)  # [B, H, W]
    C = (q[0, 0] * X * X + 2 * bc[0] * X + quad.c) + (q[1, 1] * Y * Y + 2 * bc[1] * Y) + (2 * q[0, 1] * Y) * X
    disc = Bh * Bh - A * C
    real = disc >= 0
    root = torch.sqrt(disc.clamp_min(0.0))
    qq = -(Bh + torch.where(Bh >= 0, root, -root))
    qq = torch.where(qq == 0, torch.full_like(qq, _TINY), qq)
    r1, r2 = qq / A, C / qq
    lo, hi = torch.minimum(r1, r2), torch.maximum(r1, r2)
    big = torch.full_like(lo, _BIG)
    positive = A > 0  # [B, 1, 1]
    s_in = torch.where(positive, torch.where(real, lo, big), -big)
    s_out = torch.where(positive, torch.where(real, hi, -big), big)
    if quad.kind == "cone" and not bool(positive.all()):
        axis_z = _rotate(R, quad.axis.to(dt)[None])[:, 0, 2, None, None]  # [B, 1, 1]
        rising = axis_z < 0  # the ray direction -e_z has object-frame axis component -axis_z
        two_sided = (~positive) & real
        s_in = torch.where(two_sided & ~rising, hi, s_in)
        s_out = torch.where(two_sided & rising, lo, s_out)
    return s_in, s_out, Q, bq


def _check_render_args(shape: str, rotations: torch.Tensor, image_size: int, supersample: int, dtype) -> None:
    check_shape(shape)
    if not isinstance(rotations, torch.Tensor):
        raise ValueError(f"rotations must be a torch.Tensor of shape (..., 3, 3), got {type(rotations).__name__}")
    check_rotation_matrix(rotations, name="rotations")
    for name, value in (("image_size", image_size), ("supersample", supersample)):
        if isinstance(value, bool) or not isinstance(value, int) or value < 1:
            raise ValueError(f"{name} must be a positive int, got {value!r}")
    if dtype not in (torch.float32, torch.float64):
        raise ValueError(f"dtype must be torch.float32 or torch.float64, got {dtype}")


def _images_per_chunk(samples_per_image: int) -> int:
    return max(1, _CHUNK_SAMPLES // samples_per_image)


def render(
    shape: str,
    rotations: torch.Tensor,
    image_size: int = 224,
    supersample: int = 2,
    dtype: torch.dtype = torch.float32,
) -> torch.Tensor:
    """Render ``shape`` at ``rotations`` ``(..., 3, 3)``: ``torch.uint8`` RGB images ``(..., H, W, 3)``.

    ``H = W = image_size``; each pixel averages ``supersample x supersample`` rays. Computation runs in
    ``dtype`` (rotations are cast to it first) on chunks of images, each restricted to the pixels its
    shapes' bounding boxes can reach; a pixel's value depends only on its own image's rotation, not on
    the batch it is rendered in.
    """
    _check_render_args(shape, rotations, image_size, supersample, dtype)
    geom = shape_geometry(shape)
    batch_shape = rotations.shape[:-2]
    R = rotations.reshape(-1, 3, 3).to(dtype)
    ss = supersample
    coords = _axis_coords(image_size * ss, dtype)
    albedo = {LABEL_BODY: geom.colour, **{p.label: p.colour for p in geom.marks}}
    albedo_t = {k: torch.tensor(v, dtype=dtype) for k, v in albedo.items()}
    out = torch.zeros(R.shape[0], image_size, image_size, 3, dtype=torch.uint8)
    per_chunk = _images_per_chunk((image_size * ss) ** 2)
    with torch.no_grad():
        for start in range(0, R.shape[0], per_chunk):
            Rc = R[start : start + per_chunk]
            i0, i1, j0, j1 = _pixel_window(geom, Rc, image_size)
            if i0 == i1 or j0 == j1:
                continue
            cast = _cast(geom, Rc, coords[j0 * ss : j1 * ss], -coords[i0 * ss : i1 * ss])
            shade = cast["shade"].view(-1, i1 - i0, ss, j1 - j0, ss)
            if len(albedo) == 1:
                colour = (shade.sum(dim=(2, 4)) / ss**2)[..., None] * albedo_t[LABEL_BODY]
            else:
                label = cast["label"].view_as(shade)
                colour = 0
                for k, a in albedo_t.items():
                    pooled = torch.where(label == k, shade, torch.zeros_like(shade)).sum(dim=(2, 4)) / ss**2
                    colour = colour + pooled[..., None] * a
            out[start : start + per_chunk, i0:i1, j0:j1] = (colour * 255.0).round_().clamp_(0, 255).to(torch.uint8)
    return out.reshape(*batch_shape, image_size, image_size, 3)


class RayHits(NamedTuple):
    """Per-pixel buffers of :func:`cast_rays`, one ray through each pixel centre.

    ``hit`` bool ``(..., H, W)``; ``depth`` ``(..., H, W)``: camera-frame ``z`` of the visible point
    (NaN where missed); ``normal`` ``(..., H, W, 3)``: its unit camera-frame outward normal (0 where
    missed); ``label`` uint8 ``(..., H, W)``: ``LABEL_BACKGROUND``, ``LABEL_BODY``, ``LABEL_MARK_DISC``
    or ``LABEL_MARK_DOT``; ``shade`` ``(..., H, W)``: the Lambertian factor (0 where missed).
    """

    hit: torch.Tensor
    depth: torch.Tensor
    normal: torch.Tensor
    label: torch.Tensor
    shade: torch.Tensor


def cast_rays(shape: str, rotations: torch.Tensor, resolution: int, dtype: torch.dtype = torch.float64) -> RayHits:
    """Cast one ray through each pixel centre of a ``resolution x resolution`` image (no anti-aliasing).

    The geometry buffers behind :func:`render` (the sample positions of ``render`` with
    ``supersample=1``), for analysis and tests. ``rotations`` ``(..., 3, 3)``.
    """
    _check_render_args(shape, rotations, resolution, 1, dtype)
    geom = shape_geometry(shape)
    batch_shape = rotations.shape[:-2]
    R = rotations.reshape(-1, 3, 3).to(dtype)
    coords = _axis_coords(resolution, dtype)
    per_chunk = _images_per_chunk(resolution**2)
    with torch.no_grad():
        parts = [_cast(geom, R[i : i + per_chunk], coords, -coords, normals=True) for i in range(0, len(R), per_chunk)]
    grid = (R.shape[0], resolution, resolution)
    cat = {
        k: torch.cat([p[k] for p in parts]) if parts else torch.zeros(*grid, *((3,) if k == "normal" else ()))
        for k in ("hit", "s", "normal", "label", "shade")
    }
    hit = cat["hit"].bool()
    depth = torch.where(hit, -cat["s"], torch.full_like(cat["s"], float("nan")))
    return RayHits(
        hit=hit.reshape(*batch_shape, resolution, resolution),
        depth=depth.reshape(*batch_shape, resolution, resolution),
        normal=cat["normal"].reshape(*batch_shape, resolution, resolution, 3),
        label=cat["label"].to(torch.uint8).reshape(*batch_shape, resolution, resolution),
        shade=cat["shade"].reshape(*batch_shape, resolution, resolution),
    )


# --------------------------------------------------------------------------------------------------
# Dataset writer
# --------------------------------------------------------------------------------------------------

DEFAULT_SPLITS = {"train": 45000, "test": 5000}  # the public release
_INFO_NAME = "render_info.json"


def _stream_seed(seed: int, split: str, shape: str) -> int:
    """A 63-bit seed from ``(seed, split, shape)`` via SHA-256 (stable across runs, unlike ``hash()``)."""
    digest = hashlib.sha256(f"image2sphere.symsol/{seed}/{split}/{shape}".encode()).digest()
    return int.from_bytes(digest[:8], "little") & ((1 << 63) - 1)


def symsol_rotations(n: int, seed: int, split: str, shape: str) -> torch.Tensor:
    """The ``n`` Haar-random rendering rotations ``(n, 3, 3)`` float64 of ``(seed, split, shape)``.

    Drawn with :func:`image2sphere.so3.random_rotations` from a generator seeded by a stable hash of
    the three; each ``(split, shape)`` has its own stream, so adding a shape changes no other.
    """
    if isinstance(n, bool) or not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be a non-negative int, got {n!r}")
    g = torch.Generator().manual_seed(_stream_seed(seed, split, check_shape(shape)))
    return random_rotations(n, generator=g, dtype=torch.float64)


def _npz_add(zf: zipfile.ZipFile, key: str, array: np.ndarray) -> None:
    """Add ``key.npy`` to an open npz (zip) file, with a fixed timestamp so that the bytes are reproducible.

    ``np.savez`` stamps members with the current time; this writes the same format (stored, zip64 forced).
    """
    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_STORED
    info.external_attr = 0o644 << 16
    with zf.open(info, mode="w", force_zip64=True) as f:
        np.lib.format.write_array(f, np.ascontiguousarray(array), allow_pickle=False)


def _check_int(name: str, value, minimum: int) -> int:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"{name} must be an int >= {minimum}, got {value!r}")
    return value


def _check_splits(splits) -> dict[str, int]:
    if splits is None:
        return dict(DEFAULT_SPLITS)
    if not isinstance(splits, dict) or not splits:
        raise ValueError(f"splits must be a non-empty dict {{name: number of images per shape}}, got {splits!r}")
    for name, n in splits.items():
        if not isinstance(name, str) or not name or name.startswith(".") or "/" in name or "\\" in name:
            raise ValueError(f"splits: invalid split name {name!r} (a plain directory name is needed)")
        _check_int(f"splits[{name!r}]", n, 1)
    return dict(splits)


def _is_complete(root: Path, params: dict) -> bool:
    """Whether ``root`` holds every file the parameters call for (npz keys and all images)."""
    for split, n in params["splits"].items():
        npz = root / split / "rotations.npz"
        images = root / split / "images"
        if not npz.is_file() or not images.is_dir():
            return False
        try:
            with zipfile.ZipFile(npz) as zf:
                keys = {name[: -len(".npy")] for name in zf.namelist()}
        except (OSError, zipfile.BadZipFile):
            return False
        if keys != set(params["shapes"]):
            return False
        present = set(os.listdir(images))
        if any(f"{shape}_{i:05d}.png" not in present for shape in params["shapes"] for i in range(n)):
            return False
    return True


def render_symsol(
    root: str | os.PathLike,
    splits: dict[str, int] | None = None,
    shapes: Sequence[str] = SHAPES,
    image_size: int = 224,
    seed: int = 0,
    supersample: int = 2,
    batch_size: int = 64,
    progress: bool = True,
    png_thread: bool | None = None,
) -> dict:
    """Render a SYMSOL-style dataset into ``root`` in the published layout (module docstring).

    ``splits`` maps split names to the number of images per shape (default: 45000 train, 5000 test,
    as published). The rotations of ``(split, shape)`` are :func:`symsol_rotations` of ``seed``, and
    the npz holds :func:`~image2sphere.data.symmetry.equivalent_rotation_sets` in float32 (NaN-padded
    for marked shapes). Equal arguments give byte-identical files; ``batch_size`` (images per
    :func:`render` call) and ``progress`` do not change the output.

    Caching and safety: ``root/render_info.json`` records the parameters. If ``root`` already holds a
    complete set with the same parameters, nothing is rendered (cache hit). If it exists with other
    parameters or other content (anything but an empty directory), ``FileExistsError`` is raised and
    nothing is touched. The set is rendered into ``root.parent / ".{root.name}.partial-<pid>"``,
    which is renamed to ``root`` only when complete and removed if rendering fails.

    ``png_thread``: encode the PNG files in a helper thread while the next batch renders. The default
    (None) uses it only if torch's intra-op threads leave a CPU free: oversubscribed cores make torch's
    thread pool crawl (10x and worse).

    Returns ``{"root", "cached", "counts": {split: {shape: n}}, "images", "rendered", "seconds",
    "images_per_second"}`` (``rendered`` is 0 on a cache hit).
    """
    root = Path(root)
    splits = _check_splits(splits)
    shapes = check_shape_list(shapes)
    _check_int("image_size", image_size, 1)
    _check_int("supersample", supersample, 1)
    _check_int("batch_size", batch_size, 1)
    _check_int("seed", seed, 0)
    params = {
        "format": "SYMSOL",
        "format_version": FORMAT_VERSION,
        "renderer_version": RENDERER_VERSION,
        "splits": splits,
        "shapes": shapes,
        "image_size": image_size,
        "supersample": supersample,
        "seed": seed,
    }
    counts = {split: dict.fromkeys(shapes, n) for split, n in splits.items()}
    total = sum(n * len(shapes) for n in splits.values())
    t0 = time.perf_counter()
    if root.exists():
        info_path = root / _INFO_NAME
        if not root.is_dir():
            raise FileExistsError(f"{root} exists and is not a directory; choose another directory or delete it")
        if info_path.is_file():
            try:
                existing = json.loads(info_path.read_text())
            except (OSError, ValueError):
                existing = None
            if existing == params and _is_complete(root, params):
                log.info("SYMSOL set in %s is complete with the same parameters: not re-rendering", root)
                return _writer_result(root, counts, total, rendered=0, seconds=time.perf_counter() - t0)
            if isinstance(existing, dict) and existing.get("format") == "SYMSOL" and existing != params:
                raise FileExistsError(
                    f"{root} holds a SYMSOL set rendered with different parameters ({existing}); "
                    "choose another directory or delete it"
                )
            raise FileExistsError(
                f"{root} holds an incomplete or unreadable SYMSOL set; choose another directory or delete it"
            )
        if any(root.iterdir()):
            raise FileExistsError(
                f"{root} already exists and is not a SYMSOL set rendered by this tool; "
                "choose another directory or delete it"
            )
    root.parent.mkdir(parents=True, exist_ok=True)
    partial = root.parent / f".{root.name}.partial-{os.getpid()}"
    if partial.exists():  # left over by an earlier, killed process with our pid: ours to remove
        shutil.rmtree(partial)
    from tqdm.auto import tqdm

    try:
        partial.mkdir()
        if png_thread is None:
            png_thread = torch.get_num_threads() < available_cpus()
        pending: list[Future] = []
        # PNG encoding (zlib, GIL released) overlaps with rendering in one helper thread
        with (
            ThreadPoolExecutor(max_workers=1) if png_thread else _InlineExecutor() as pool,
            tqdm(total=total, disable=not progress, desc=f"rendering SYMSOL into {root}", unit="img") as bar,
        ):
            for split, n in splits.items():
                images_dir = partial / split / "images"
                images_dir.mkdir(parents=True)
                npz_path = partial / split / "rotations.npz"
                with zipfile.ZipFile(npz_path, mode="w", allowZip64=True) as npz:
                    for shape in shapes:  # one shape's array in memory at a time (cyl: 1.2 GB for 45k images)
                        bar.set_postfix(split=split, shape=shape)
                        R = symsol_rotations(n, seed, split, shape)
                        sets, _ = equivalent_rotation_sets(shape, R, dtype=torch.float32)
                        _npz_add(npz, shape, sets.numpy())
                        del sets
                        for start in range(0, n, batch_size):
                            images = render(shape, R[start : start + batch_size], image_size, supersample).numpy()
                            paths = [images_dir / f"{shape}_{i:05d}.png" for i in range(start, start + len(images))]
                            pending.append(pool.submit(_save_pngs, paths, images))
                            while len(pending) > 2:  # bound the images held in memory
                                pending.pop(0).result()
                            bar.update(len(images))
            while pending:
                pending.pop(0).result()
        (partial / _INFO_NAME).write_text(json.dumps(params, indent=2, sort_keys=True) + "\n")
        try:
            os.rename(partial, root)  # atomic; replaces ``root`` only if it is an empty directory
        except OSError as err:
            raise FileExistsError(
                f"{root} appeared or changed while rendering; the new set was not moved there. "
                "Choose another directory or delete it"
            ) from err
    except BaseException:
        shutil.rmtree(partial, ignore_errors=True)
        raise
    return _writer_result(root, counts, total, rendered=total, seconds=time.perf_counter() - t0)


def _writer_result(root: Path, counts: dict, total: int, rendered: int, seconds: float) -> dict:
    """What :func:`render_symsol` returns; ``rendered == 0`` is a cache hit."""
    speed = 0.0 if rendered == 0 else (rendered / seconds if seconds > 0 else float("inf"))
    return {
        "root": str(root),
        "cached": rendered == 0,
        "counts": counts,
        "images": total,
        "rendered": rendered,
        "seconds": seconds,
        "images_per_second": speed,
    }


class _InlineExecutor:
    """The ``submit`` / context-manager subset of an executor, running each call at once."""

    def submit(self, fn, *args) -> Future:
        future: Future = Future()
        future.set_result(fn(*args))
        return future

    def __enter__(self) -> _InlineExecutor:
        return self

    def __exit__(self, *exc) -> None:
        return None


def _save_pngs(paths: list[Path], images: np.ndarray) -> None:
    """Write RGB ``images`` ``(N, H, W, 3)`` uint8 as PNG files (Pillow's defaults: deterministic bytes)."""
    from PIL import Image

    for path, image in zip(paths, images, strict=True):
        Image.fromarray(image).save(path, format="PNG")


# --------------------------------------------------------------------------------------------------
# Command line
# --------------------------------------------------------------------------------------------------


def _build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="python -m image2sphere.data.render",
        description="Render a SYMSOL-style dataset (published layout: {split}/images/{shape}_{i:05d}.png, "
        "{split}/rotations.npz) into ROOT. Re-running with the same arguments is a no-op.",
    )
    p.add_argument("root", metavar="ROOT", help="output directory (must not exist, be empty, or hold this set)")
    p.add_argument("--train", type=int, default=DEFAULT_SPLITS["train"], help="train images per shape (0: none)")
    p.add_argument("--test", type=int, default=DEFAULT_SPLITS["test"], help="test images per shape (0: none)")
    p.add_argument("--shapes", nargs="+", default=list(SHAPES), metavar="SHAPE", help=f"any of {' '.join(SHAPES)}")
    p.add_argument("--image-size", type=int, default=224, help="image height and width in pixels")
    p.add_argument("--supersample", type=int, default=2, help="anti-aliasing: rays per pixel along each axis")
    p.add_argument("--seed", type=int, default=0, help="random seed (>= 0)")
    p.add_argument("--batch-size", type=int, default=64, help="images per render call (memory, not output)")
    p.add_argument(
        "--threads",
        type=int,
        default=None,
        help="torch intra-op threads (default: CPUs - 1, leaving one CPU to encode PNG files)",
    )
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    return p


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status (argument errors exit with status 2).

    Sets torch's intra-op thread count (``--threads``) for the rest of the process.
    """
    parser = _build_parser()
    args = parser.parse_args(argv)
    unknown = [s for s in args.shapes if s not in SHAPES]
    if unknown:
        parser.error(f"unknown shape(s) {' '.join(unknown)}; valid shapes are {' '.join(SHAPES)}")
    if len(set(args.shapes)) != len(args.shapes):
        parser.error(f"--shapes lists a shape twice: {' '.join(args.shapes)}")
    for name in ("train", "test"):
        if getattr(args, name) < 0:
            parser.error(f"--{name} must be >= 0, got {getattr(args, name)}")
    for name in ("image_size", "supersample", "batch_size"):
        if getattr(args, name) < 1:
            parser.error(f"--{name.replace('_', '-')} must be >= 1, got {getattr(args, name)}")
    if args.seed < 0:
        parser.error(f"--seed must be >= 0, got {args.seed}")
    if args.threads is not None and args.threads < 1:
        parser.error(f"--threads must be >= 1, got {args.threads}")
    splits = {name: n for name, n in (("train", args.train), ("test", args.test)) if n > 0}
    if not splits:
        parser.error("--train and --test are both 0: nothing to render")
    torch.set_num_threads(args.threads or max(1, available_cpus() - 1))
    try:
        result = render_symsol(
            args.root,
            splits=splits,
            shapes=args.shapes,
            image_size=args.image_size,
            seed=args.seed,
            supersample=args.supersample,
            batch_size=args.batch_size,
            progress=not args.no_progress,
        )
    except FileExistsError as err:
        print(f"error: {err}", file=sys.stderr)
        return 1
    if result["cached"]:
        print(f"{args.root}: complete set with the same parameters already there ({result['images']} images)")
    else:
        print(
            f"rendered {result['rendered']} images into {args.root} in {result['seconds']:.1f} s: "
            f"{result['images_per_second']:.1f} images/second"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())
