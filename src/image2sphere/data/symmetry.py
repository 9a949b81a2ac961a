"""The symmetries of the SYMSOL shapes: their groups, mark visibility and the equivalent rotations
(the SYMSOL ground truth). The shapes themselves are in :mod:`image2sphere.data.shapes`.

Conventions
-----------
* Rotation matrices ``(..., 3, 3)`` act on column vectors: ``x_camera = R @ x_object`` (docs/conventions.md).
* Symmetries act on the right: ``S`` maps the object onto itself (``x -> S x``), so the rotations ``R``
  and ``R @ S`` give the same image (``x_cam = R S x_obj``).
* Groups are float64 tensors ``(G, 3, 3)`` whose element 0 is exactly the identity.

Symmetry sets (``symmetry_group``)
----------------------------------
========  =============================================
shape     symmetry set returned by ``symmetry_group``
========  =============================================
tet       scipy ``create_group("T")``, 12
cube      scipy ``create_group("O")``, 24
icosa     scipy ``create_group("I")``, 60
cone      ``Ry(k deg)``, k = 0..359: 360
cyl       ``Ry(k deg)`` then ``Ry(k deg) @ Rx(180 deg)``,
          k = 0..359: 720
tetX      as tet (12)
cylO      as cyl (720)
sphereX   identity, then the SO(3) HEALPix grid of
          level 1 (pixel-major): 577
========  =============================================

The groups of the polyhedra are exactly scipy's, because the vertices are built as orbits of those
groups. The rotations of cone, cylinder and sphere form continuous groups; the sets above discretise
them (the SO(3) grid is not closed under products, the others are).

Equivalent rotations (the SYMSOL ground truth), ``M`` per shape
---------------------------------------------------------------
:func:`equivalent_rotations` returns ``(M, 3, 3)``; element 0 is ``R`` itself, the others are
``R @ S`` in the order of ``symmetry_group``:

* tet ``M = 12``, cube ``M = 24``, icosa ``M = 60``, cone ``M = 360``, cyl ``M = 720``: all ``R @ S``.
* Marked shapes (SYMSOL II rule): if the mark is visible at ``R`` (:func:`mark_visible`), ``M = 1``
  (only ``R``). If it is hidden, the set is ``{R @ S : S in symmetry_group(shape), mark hidden at
  R @ S}`` (all of these give the same image). Hence tetX: ``M = 1`` or ``M = 3 h`` where
  ``h`` in 1..3 is the number of faces hidden at ``R`` (generic views show 1 to 3 faces); cylO:
  ``M = 1`` or up to 720 (about 280 in generic views: the mark spans about 40 degrees of the side;
  720 when looking along the axis, where the whole side is grazing); sphereX: ``M = 1`` or up to 577
  (about 210). ``M`` varies between images, so the dataset arrays are NaN-padded (see
  :func:`equivalent_rotation_sets`).

Visibility is analytic (convex solids, see above): a flat-face mark with normal ``n`` is visible iff
``(R n)_z > 0``; a spherical-cap part of angular radius ``theta`` around the unit vector ``n`` iff
``(R n)_z > -sin(theta)``; a cylinder-side part whose normals are ``n(phi) = (cos phi, 0, sin phi)``,
``phi in [phi0 - dphi, phi0 + dphi]``, iff the maximum of the sinusoid ``(R n(phi))_z`` over that
interval is ``> 0``. The mark is visible iff any of its parts is.
"""

from __future__ import annotations

import math
from functools import cache

import numpy as np
import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.data.shapes import SYMSOL_II_SHAPES, ShapeGeometry, check_shape, exact_matmul3, shape_geometry
from image2sphere.so3.groups import rotation_group
from image2sphere.so3.rotations import rotation_about_axis

__all__ = ["equivalent_rotation_sets", "equivalent_rotations", "mark_visible", "symmetry_group"]


@cache
def _symmetry_set_np(shape: str) -> np.ndarray:
    base = {"tetX": "tet", "cylO": "cyl"}.get(shape, shape)
    if base == "tet":
        return rotation_group("T").numpy()
    if base == "cube":
        return rotation_group("O").numpy()
    if base == "icosa":
        return rotation_group("I").numpy()
    if base in ("cone", "cyl"):
        k = np.arange(360)
        Ry = rotation_about_axis("y", torch.from_numpy(np.deg2rad(k.astype(np.float64)))).numpy()
        Ry[np.abs(Ry) < 1e-15] = 0.0  # exact identity and quarter turns
        if base == "cone":
            return Ry
        flip = np.diag([1.0, -1.0, -1.0])  # Rx(180 deg), exact
        return np.concatenate([Ry, Ry @ flip])
    if base == "sphereX":
        from image2sphere.so3.grid import so3_healpix_grid

        grid = so3_healpix_grid(1, dtype=torch.float64).numpy()  # [576, 3, 3], no identity in it
        return np.concatenate([np.eye(3)[None], grid])
    raise AssertionError(shape)


def symmetry_group(shape: str) -> torch.Tensor:
    """The (discretised) rotation group of the shape's unmarked body, ``(G, 3, 3)`` float64.

    ``G[0]`` is exactly the identity. Sizes: tet/tetX 12, cube 24, icosa 60, cone 360, cyl/cylO 720,
    sphereX 577 (identity + SO(3) HEALPix level 1). For marked shapes the mark breaks these
    symmetries; :func:`equivalent_rotations` applies the SYMSOL II rule.
    """
    return torch.from_numpy(_symmetry_set_np(check_shape(shape)).copy())


# --------------------------------------------------------------------------------------------------
# Visibility and equivalent rotations
# --------------------------------------------------------------------------------------------------


def _check_rotations(rotations: torch.Tensor, name: str = "rotations") -> torch.Tensor:
    from image2sphere.so3.rotations import check_rotation_matrix

    return check_rotation_matrix(rotations, name=name)


def _visible_from_zrow(geom: ShapeGeometry, zrow: torch.Tensor) -> torch.Tensor:
    """Mark visibility from the third rows ``(..., 3)`` of the rotations (float64)."""
    visible = torch.zeros(zrow.shape[:-1], dtype=torch.bool, device=zrow.device)
    r0, r1, r2 = zrow.unbind(-1)
    for part in geom.marks:
        n = part.normal.tolist()
        if geom.mark_kind == "face":
            visible |= (r0 * n[0] + r1 * n[1] + r2 * n[2]) > 0
        elif geom.mark_kind == "cap":
            visible |= (r0 * n[0] + r1 * n[1] + r2 * n[2]) > -math.sin(part.half_angle)
        else:  # band: (R n(phi))_z = r0 cos(phi) + r2 sin(phi) = A cos(phi - psi)
            amplitude = torch.hypot(r0, r2)
            psi = torch.atan2(r2, r0)
            phi0 = math.atan2(n[2], n[0])
            gap = torch.remainder(phi0 - psi + math.pi, 2 * math.pi) - math.pi  # in [-pi, pi)
            nearest = (gap.abs() - part.half_angle).clamp_min(0.0)  # distance from psi to the interval
            visible |= amplitude * torch.cos(nearest) > 0
    return visible


def mark_visible(shape: str, rotations: torch.Tensor) -> torch.Tensor:
    """Whether the mark of a marked shape is visible at each rotation: bool ``(...)`` for ``(..., 3, 3)``.

    Analytic (see the module docstring); computed in float64. Raises ``ValueError`` for unmarked shapes.
    """
    geom = shape_geometry(check_shape(shape))
    if not geom.marks:
        raise ConfigError(f"shape {shape!r} has no mark; marked shapes are {', '.join(SYMSOL_II_SHAPES)}")
    _check_rotations(rotations)
    return _visible_from_zrow(geom, rotations[..., 2, :].to(torch.float64))


def _equivalence_mask(shape: str, rotations: torch.Tensor) -> torch.Tensor:
    """``(N, G)`` bool: which ``R_n @ S_g`` belong to the equivalent set of ``R_n`` (column 0 always)."""
    geom = shape_geometry(shape)
    G = _symmetry_set_np(shape)
    n = rotations.shape[0]
    if not geom.marks:
        return torch.ones(n, len(G), dtype=torch.bool)
    group = torch.from_numpy(G)
    zrow = rotations[:, 2, :].to(torch.float64)  # [N, 3]
    visible = _visible_from_zrow(geom, zrow)  # [N]
    # third row of R @ S = R[2, :] @ S
    z = zrow[:, None, :, None]  # [N, 1, 3, 1]
    zrow_rs = (
        z[..., 0, :] * group[None, :, 0, :] + z[..., 1, :] * group[None, :, 1, :] + z[..., 2, :] * group[None, :, 2, :]
    )  # [N, G, 3]
    mask = ~_visible_from_zrow(geom, zrow_rs)  # [N, G]
    mask[visible] = False
    mask[:, 0] = True
    return mask


def equivalent_rotation_sets(
    shape: str, rotations: torch.Tensor, dtype: torch.dtype | None = None, chunk_size: int = 512
) -> tuple[torch.Tensor, torch.Tensor]:
    """Equivalent rotations of many images: ``(N, M_max, 3, 3)`` NaN-padded, and the counts ``(N,)``.

    ``rotations`` ``(N, 3, 3)``. Row ``n`` holds the ``counts[n]`` members of
    ``equivalent_rotations(shape, rotations[n])`` followed by all-NaN matrices (padding).
    ``M_max = counts.max()``: the group size for unmarked shapes. ``[:, 0]`` equals ``rotations``
    exactly (cast to ``dtype``, default ``rotations.dtype``). Products are computed in float64.
    """
    check_shape(shape)
    if rotations.ndim != 3:
        raise ConfigError(f"rotations must have shape (N, 3, 3), got {tuple(rotations.shape)}")
    check_int("chunk_size", chunk_size, 1)
    _check_rotations(rotations)
    dtype = dtype or rotations.dtype
    group = torch.from_numpy(_symmetry_set_np(shape))
    n = rotations.shape[0]
    masks = [_equivalence_mask(shape, rotations[i : i + chunk_size]) for i in range(0, n, chunk_size)]
    mask = torch.cat(masks) if masks else torch.zeros(0, len(group), dtype=torch.bool)
    counts = mask.sum(1)
    m_max = int(counts.max()) if n else (1 if shape_geometry(shape).marks else len(group))
    out = torch.full((n, m_max, 3, 3), float("nan"), dtype=dtype)
    for i in range(0, n, chunk_size):
        R = rotations[i : i + chunk_size].to(torch.float64)
        m = mask[i : i + chunk_size]
        if bool(m.all()):
            out[i : i + chunk_size] = exact_matmul3(R[:, None], group[None]).to(dtype)
            continue
        order = torch.argsort((~m).to(torch.int8), dim=1, stable=True)[:, :m_max]  # members first
        S = group[order]  # [n, m_max, 3, 3]
        prod = exact_matmul3(R[:, None], S)
        keep = torch.arange(m_max)[None, :] < counts[i : i + chunk_size, None]
        out[i : i + chunk_size] = torch.where(keep[..., None, None], prod, float("nan")).to(dtype)
    if n:
        out[:, 0] = rotations.to(dtype)
    return out, counts


def equivalent_rotations(shape: str, rotation: torch.Tensor) -> torch.Tensor:
    """The SYMSOL equivalent rotations of one image, ``(M, 3, 3)`` in ``rotation``'s dtype.

    ``rotation`` ``(3, 3)``; element 0 is exactly ``rotation``, the others are ``rotation @ S``; ``M``
    per shape is given in the module docstring.
    """
    if not isinstance(rotation, torch.Tensor) or rotation.shape != (3, 3):
        shape_desc = tuple(rotation.shape) if isinstance(rotation, torch.Tensor) else type(rotation).__name__
        raise ConfigError(f"rotation must be a (3, 3) tensor, got {shape_desc}")
    sets, counts = equivalent_rotation_sets(shape, rotation[None])
    return sets[0, : int(counts[0])]
