"""Vectorised ray-casting renderer of the SYMSOL shapes (the writer of the SYMSOL layout is
:mod:`image2sphere.data.render`).

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
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.data.shapes import (
    CONE_APEX_HEIGHT,
    CONE_BASE_DEPTH,
    CONE_BASE_RADIUS,
    CYL_HALF_HEIGHT,
    CYL_RADIUS,
    SPHERE_RADIUS,
    ShapeGeometry,
    check_shape,
    exact_matmul3,
    shape_geometry,
)
from image2sphere.so3.rotations import check_rotation_matrix

__all__ = [
    "AMBIENT",
    "DIFFUSE",
    "LABEL_BACKGROUND",
    "LABEL_BODY",
    "LABEL_MARK_DISC",
    "LABEL_MARK_DOT",
    "LIGHT_DIRECTION",
    "RayHits",
    "cast_rays",
    "render",
]

LIGHT_DIRECTION = tuple(v / math.sqrt(0.3**2 + 0.5**2 + 1.0) for v in (-0.3, 0.5, 1.0))  # camera frame, unit
AMBIENT = 0.3
DIFFUSE = 0.7

LABEL_BACKGROUND, LABEL_BODY, LABEL_MARK_DISC, LABEL_MARK_DOT = 0, 1, 2, 3

_BIG = 1e30  # stands for an infinite ray parameter
_TINY = 1e-12  # |n_z| below this counts as edge-on
_CHUNK_SAMPLES = 1 << 18  # rays per chunk: keeps the working set of each pass in cache (~1 MB per buffer)


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
        raise ConfigError(f"rotations must be a torch.Tensor of shape (..., 3, 3), got {type(rotations).__name__}")
    check_rotation_matrix(rotations, name="rotations")
    check_int("image_size", image_size, 1)
    check_int("supersample", supersample, 1)
    if dtype not in (torch.float32, torch.float64):
        raise ConfigError(f"dtype must be torch.float32 or torch.float64, got {dtype}")


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
