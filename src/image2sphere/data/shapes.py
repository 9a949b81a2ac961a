"""The eight SYMSOL shapes: geometry, symmetry groups, marks, mark visibility and equivalent rotations.

Conventions
-----------
* Rotation matrices ``(..., 3, 3)`` act on column vectors: ``x_camera = R @ x_object`` (docs/conventions.md).
* Object frame: ``y`` is the axis of the cone (apex on ``+y``) and of the cylinder. Lengths are in units
  of the image half-width: the renderer's orthographic image covers ``[-1, 1]^2`` of the camera
  ``x-y`` plane, and every shape lies inside the ball of radius :data:`BOUND_RADIUS` (0.85) around the
  origin, so it stays inside the image at every rotation.
* Camera frame: ``x`` right, ``y`` up, ``z`` toward the viewer; rays travel along ``-z``. Every shape is
  a convex solid, so a point of its surface is visible iff its outward camera-frame normal has
  ``z > 0`` (``z = 0`` is grazing and counts as hidden).
* Symmetries act on the right: ``S`` maps the object onto itself (``x -> S x``), so the rotations ``R``
  and ``R @ S`` give the same image (``x_cam = R S x_obj``).
* Groups are float64 tensors ``(G, 3, 3)`` whose element 0 is exactly the identity.

Shapes (``SHAPES``; SYMSOL I = the first five, SYMSOL II = the last three)
-------------------------------------------------------------------------
========  ===========================================  =============================================
shape     solid                                        symmetry set returned by ``symmetry_group``
========  ===========================================  =============================================
tet       regular tetrahedron, vertices = orbit of     scipy ``create_group("T")``, 12
          (1, 1, 1) under T
cube      cube, vertices (+-1, +-1, +-1)               scipy ``create_group("O")``, 24
icosa     regular icosahedron, vertices = the 5-fold   scipy ``create_group("I")``, 60
          axes of scipy's I group
cone      circular cone about y, apex on +y            ``Ry(k deg)``, k = 0..359: 360
cyl       finite circular cylinder about y             ``Ry(k deg)`` then ``Ry(k deg) @ Rx(180 deg)``,
                                                       k = 0..359: 720
tetX      tet with a mark on one face                  as tet (12)
cylO      cyl with a mark on its side, above           as cyl (720)
          mid-height
sphereX   sphere with a mark                           identity, then the SO(3) HEALPix grid of
                                                       level 1 (pixel-major): 577
========  ===========================================  =============================================

The groups of the polyhedra are exactly scipy's, because the vertices are built as orbits of those
groups. The rotations of cone, cylinder and sphere form continuous groups; the sets above discretise
them (the SO(3) grid is not closed under products, the others are).

Marks
-----
A mark is a "comet": a disc of colour :data:`MARK_DISC_COLOUR` plus a smaller dot of
:data:`MARK_DOT_COLOUR` beside it, so that no rotation but the identity maps the mark onto itself.
Each part is the set of surface points within Euclidean distance ``rho`` of its centre (a point on
the surface), i.e. ball ``∩`` surface. Every part lies inside one smooth piece of the surface: on
tetX both parts lie on one face, away from the face centroid (so the 3-fold rotation about that face
moves them) and farther than ``rho`` from every other face plane; on cylO both lie on the side, above
mid-height (so the flips ``Ry @ Rx(180)`` move them) and farther than ``rho`` from the caps.

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
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from image2sphere.so3.groups import rotation_group
from image2sphere.so3.rotations import rotation_about_axis

__all__ = [
    "BOUND_RADIUS",
    "MARK_DISC_COLOUR",
    "MARK_DOT_COLOUR",
    "SHAPES",
    "SYMSOL_I_SHAPES",
    "SYMSOL_II_SHAPES",
    "MarkPart",
    "Quadric",
    "ShapeGeometry",
    "check_shape",
    "check_shape_list",
    "equivalent_rotation_sets",
    "equivalent_rotations",
    "mark_visible",
    "shape_geometry",
    "symmetry_group",
]

SHAPES: tuple[str, ...] = ("tet", "cube", "icosa", "cone", "cyl", "tetX", "cylO", "sphereX")
SYMSOL_I_SHAPES: tuple[str, ...] = SHAPES[:5]
SYMSOL_II_SHAPES: tuple[str, ...] = SHAPES[5:]

BOUND_RADIUS = 0.85  # every shape lies in this ball (image half-width = 1)

MARK_DISC_COLOUR = (0.90, 0.10, 0.10)  # red
MARK_DOT_COLOUR = (0.10, 0.25, 0.95)  # blue

_COLOURS = {
    "tet": (0.95, 0.70, 0.25),
    "cube": (0.30, 0.60, 0.95),
    "icosa": (0.45, 0.85, 0.40),
    "cone": (0.85, 0.45, 0.85),
    "cyl": (0.95, 0.85, 0.30),
    "tetX": (0.95, 0.70, 0.25),
    "cylO": (0.95, 0.85, 0.30),
    "sphereX": (0.80, 0.80, 0.80),
}

# Dimensions (object units, image half-width = 1).
CONE_BASE_RADIUS = 0.55
CONE_APEX_HEIGHT = BOUND_RADIUS  # apex at y = +0.85
CONE_BASE_DEPTH = math.sqrt(BOUND_RADIUS**2 - CONE_BASE_RADIUS**2)  # base plane at y = -0.648
CYL_RADIUS = 0.5
CYL_HALF_HEIGHT = math.sqrt(BOUND_RADIUS**2 - CYL_RADIUS**2)  # 0.687
SPHERE_RADIUS = 0.7


@dataclass(frozen=True)
class MarkPart:
    """One part of a mark: the surface points within ``radius`` of ``centre`` (a surface point).

    ``centre`` ``(3,)`` float64, object frame. ``label`` is the renderer's label of the part's pixels.
    ``normal`` ``(3,)`` is the face normal (flat marks), the unit vector to the centre (sphere caps) or
    the side normal at the centre (cylinder); ``half_angle`` is the cap's angular radius (sphere) or
    the half-width ``dphi`` of the interval of side angles (cylinder), 0 for flat marks.
    """

    centre: torch.Tensor
    radius: float
    colour: tuple[float, float, float]
    label: int
    normal: torch.Tensor
    half_angle: float


@dataclass(frozen=True)
class Quadric:
    """The solid ``q(x) = x^T Q x + 2 b.x + c <= 0`` (object frame), ``Q`` ``(3, 3)``, ``b`` ``(3,)``.

    ``kind`` is ``"sphere"``, ``"cylinder"`` or ``"cone"``. For the cone ``q <= 0`` is a double cone;
    the solid keeps the nappe below the apex, toward ``-axis`` (the renderer picks the root(s) on it).
    """

    kind: str
    Q: torch.Tensor
    b: torch.Tensor
    c: float
    axis: torch.Tensor


@dataclass(frozen=True)
class ShapeGeometry:
    """A convex solid: the intersection of half-spaces ``n_f . x <= h_f`` and at most one quadric.

    ``plane_normals`` ``(F, 3)`` unit outward normals and ``plane_offsets`` ``(F,)`` (float64, object
    frame); ``vertices`` ``(V, 3)`` for polyhedra, else None; ``colour`` the body's RGB albedo in
    ``[0, 1]``; ``marks`` the mark's parts (empty for unmarked shapes) and ``mark_kind`` ``"face"``,
    ``"cap"``, ``"band"`` or None.
    """

    name: str
    colour: tuple[float, float, float]
    plane_normals: torch.Tensor
    plane_offsets: torch.Tensor
    quadric: Quadric | None
    vertices: torch.Tensor | None
    marks: tuple[MarkPart, ...]
    mark_kind: str | None


def check_shape(shape: str) -> str:
    """Return ``shape`` or raise ``ValueError`` listing the valid names."""
    if not isinstance(shape, str) or shape not in SHAPES:
        raise ValueError(f"shape must be one of {', '.join(SHAPES)}; got {shape!r}")
    return shape


def check_shape_list(shapes, key: str = "shapes") -> list[str]:
    """``shapes`` as a list, or ``ValueError`` naming ``key`` unless it is a non-empty sequence of distinct names."""
    if isinstance(shapes, str) or not isinstance(shapes, Sequence) or not shapes:
        raise ValueError(f"{key} must be a non-empty sequence of names from {', '.join(SHAPES)}; got {shapes!r}")
    unknown = [s for s in shapes if s not in SHAPES]
    if unknown:
        raise ValueError(f"{key}: unknown shape(s) {unknown}; valid shapes are {', '.join(SHAPES)}")
    if len(set(shapes)) != len(shapes):
        raise ValueError(f"{key}: duplicate names in {list(shapes)}")
    return list(shapes)


# --------------------------------------------------------------------------------------------------
# Groups
# --------------------------------------------------------------------------------------------------


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
# Geometry
# --------------------------------------------------------------------------------------------------


def _unique_rows(x: np.ndarray, decimals: int = 9) -> np.ndarray:
    _, idx = np.unique(np.round(x, decimals), axis=0, return_index=True)
    return x[np.sort(idx)]


def _polyhedron_vertices(base: str) -> np.ndarray:
    if base == "tet":
        G = rotation_group("T").numpy()
        v = _unique_rows(G @ np.array([1.0, 1.0, 1.0]))
        expected = 4
    elif base == "cube":
        G = rotation_group("O").numpy()
        v = _unique_rows(G @ np.array([1.0, 1.0, 1.0]))
        expected = 8
    else:
        from scipy.spatial.transform import Rotation

        G = rotation_group("I").numpy()
        rotvec = Rotation.from_matrix(G).as_rotvec()  # [60, 3]
        angle = np.linalg.norm(rotvec, axis=1)
        five_fold = np.abs(angle - 2 * np.pi / 5) < 1e-6  # 72 deg about +-axis: 12 elements
        v = rotvec[five_fold] / angle[five_fold, None]
        expected = 12
    if len(v) != expected:
        raise RuntimeError(f"{base}: expected {expected} vertices, got {len(v)}")
    return v * (BOUND_RADIUS / np.linalg.norm(v, axis=1, keepdims=True))


def _face_planes(vertices: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Unit outward normals ``(F, 3)`` and offsets ``(F,)`` of the convex hull, coplanar triangles merged."""
    from scipy.spatial import ConvexHull

    eq = ConvexHull(vertices).equations  # [T, 4]: n . x + e <= 0 inside
    normals, offsets = eq[:, :3], -eq[:, 3]
    scale = np.linalg.norm(normals, axis=1)
    normals, offsets = normals / scale[:, None], offsets / scale
    _, idx = np.unique(np.round(normals, 7), axis=0, return_index=True)
    idx = np.sort(idx)
    return normals[idx], offsets[idx]


def _as_t(x) -> torch.Tensor:
    return torch.as_tensor(np.asarray(x, dtype=np.float64))


def _unit(v: np.ndarray) -> np.ndarray:
    return v / np.linalg.norm(v)


@cache
def shape_geometry(shape: str) -> ShapeGeometry:
    """The solid, colour and mark of ``shape`` (see the module docstring); cached, do not modify."""
    shape = check_shape(shape)
    colour = _COLOURS[shape]
    marks: list[MarkPart] = []
    mark_kind = None
    quadric = None
    vertices = None
    ey = np.array([0.0, 1.0, 0.0])
    if shape in ("tet", "cube", "icosa", "tetX"):
        vertices = _polyhedron_vertices("tet" if shape == "tetX" else shape)
        normals, offsets = _face_planes(vertices)
        if shape == "tetX":
            mark_kind = "face"
            marks = _tet_mark(vertices, normals, offsets)
    elif shape == "cone":
        k2 = (CONE_BASE_RADIUS / (CONE_APEX_HEIGHT + CONE_BASE_DEPTH)) ** 2
        a = CONE_APEX_HEIGHT
        # q = |x|^2 - (y)^2 - k^2 (a - y)^2 with y = axis . x
        Q = np.eye(3) - (1 + k2) * np.outer(ey, ey)
        quadric = Quadric("cone", _as_t(Q), _as_t(k2 * a * ey), -k2 * a * a, _as_t(ey))
        normals = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])  # apex plane (keeps the lower nappe), base
        offsets = np.array([CONE_APEX_HEIGHT, CONE_BASE_DEPTH])
    elif shape in ("cyl", "cylO"):
        Q = np.eye(3) - np.outer(ey, ey)
        quadric = Quadric("cylinder", _as_t(Q), _as_t(np.zeros(3)), -(CYL_RADIUS**2), _as_t(ey))
        normals = np.array([[0.0, 1.0, 0.0], [0.0, -1.0, 0.0]])
        offsets = np.array([CYL_HALF_HEIGHT, CYL_HALF_HEIGHT])
        if shape == "cylO":
            mark_kind = "band"
            marks = _cyl_mark()
    else:  # sphereX
        quadric = Quadric("sphere", _as_t(np.eye(3)), _as_t(np.zeros(3)), -(SPHERE_RADIUS**2), _as_t(ey))
        normals, offsets = np.zeros((0, 3)), np.zeros(0)
        mark_kind = "cap"
        marks = _sphere_mark()
    return ShapeGeometry(
        name=shape,
        colour=colour,
        plane_normals=_as_t(normals),
        plane_offsets=_as_t(offsets),
        quadric=quadric,
        vertices=None if vertices is None else _as_t(vertices),
        marks=tuple(marks),
        mark_kind=mark_kind,
    )


_DISC_LABEL, _DOT_LABEL = 2, 3


def _tet_mark(vertices: np.ndarray, normals: np.ndarray, offsets: np.ndarray) -> list[MarkPart]:
    f = int(np.argmax(normals @ np.array([0.1, 0.2, 1.0])))  # the face facing the camera at R = I
    n = normals[f]
    on_face = np.abs(vertices @ n - offsets[f]) < 1e-9
    face_vertices = vertices[on_face]  # [3, 3]
    centroid = face_vertices.mean(0)
    top = face_vertices[np.argmax(face_vertices[:, 1])]
    u = _unit(top - centroid)  # in-face, toward a vertex
    w = np.cross(n, u)  # in-face, perpendicular to u
    disc = centroid + 0.12 * u - 0.03 * w
    dot = disc + 0.19 * w + 0.02 * u
    parts = [(disc, 0.12, MARK_DISC_COLOUR, _DISC_LABEL), (dot, 0.055, MARK_DOT_COLOUR, _DOT_LABEL)]
    out = []
    others = np.arange(len(normals)) != f
    for centre, rho, col, label in parts:
        clearance = (offsets[others] - normals[others] @ centre).min()  # distance to the other face planes
        if clearance < rho + 0.02:
            raise RuntimeError(f"tetX mark part at {centre} reaches another face ({clearance:.3f} < {rho})")
        out.append(MarkPart(_as_t(centre), rho, col, label, _as_t(n), 0.0))
    return out


def _cyl_mark() -> list[MarkPart]:
    out = []
    # (phi, y, rho): side point (r cos phi, y, r sin phi); phi = pi/2 faces the camera at R = I.
    for phi, y, rho, col, label in (
        (math.pi / 2, 0.25, 0.13, MARK_DISC_COLOUR, _DISC_LABEL),
        (math.pi / 2 + 0.32, 0.42, 0.06, MARK_DOT_COLOUR, _DOT_LABEL),
    ):
        if abs(y) + rho > CYL_HALF_HEIGHT - 0.02 or abs(y) < rho:
            raise RuntimeError("cylO mark part reaches a cap or mid-height")
        normal = np.array([math.cos(phi), 0.0, math.sin(phi)])
        centre = np.array([CYL_RADIUS * math.cos(phi), y, CYL_RADIUS * math.sin(phi)])
        half_angle = 2 * math.asin(rho / (2 * CYL_RADIUS))  # widest at the centre's height
        out.append(MarkPart(_as_t(centre), rho, col, label, _as_t(normal), half_angle))
    return out


def _sphere_mark() -> list[MarkPart]:
    out = []
    disc_dir = np.array([0.0, 0.0, 1.0])  # faces the camera at R = I
    dot_dir = _unit(np.array([0.12, 0.33, 0.94]))
    for direction, rho, col, label in (
        (disc_dir, 0.15, MARK_DISC_COLOUR, _DISC_LABEL),
        (dot_dir, 0.07, MARK_DOT_COLOUR, _DOT_LABEL),
    ):
        half_angle = 2 * math.asin(rho / (2 * SPHERE_RADIUS))  # ball of radius rho meets the sphere in a cap
        out.append(MarkPart(_as_t(SPHERE_RADIUS * direction), rho, col, label, _as_t(direction), half_angle))
    return out


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
        raise ValueError(f"shape {shape!r} has no mark; marked shapes are {', '.join(SYMSOL_II_SHAPES)}")
    _check_rotations(rotations)
    return _visible_from_zrow(geom, rotations[..., 2, :].to(torch.float64))


def exact_matmul3(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``A @ B`` for broadcastable ``(..., 3, 3)`` stacks, as explicit sums (bit-identical for any batch)."""
    return (
        A[..., :, 0, None] * B[..., 0, None, :]
        + A[..., :, 1, None] * B[..., 1, None, :]
        + A[..., :, 2, None] * B[..., 2, None, :]
    )


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
        raise ValueError(f"rotations must have shape (N, 3, 3), got {tuple(rotations.shape)}")
    if not isinstance(chunk_size, int) or chunk_size < 1:
        raise ValueError(f"chunk_size must be a positive int, got {chunk_size!r}")
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
        raise ValueError(f"rotation must be a (3, 3) tensor, got {shape_desc}")
    sets, counts = equivalent_rotation_sets(shape, rotation[None])
    return sets[0, : int(counts[0])]
