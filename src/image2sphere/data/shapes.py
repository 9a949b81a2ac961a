"""The eight SYMSOL shapes: geometry, colours and marks (their symmetries are in :mod:`image2sphere.data.symmetry`).

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

Shapes (``SHAPES``; SYMSOL I = the first five, SYMSOL II = the last three)
-------------------------------------------------------------------------
========  ===========================================
shape     solid
========  ===========================================
tet       regular tetrahedron, vertices = orbit of
          (1, 1, 1) under T
cube      cube, vertices (+-1, +-1, +-1)
icosa     regular icosahedron, vertices = the 5-fold
          axes of scipy's I group
cone      circular cone about y, apex on +y
cyl       finite circular cylinder about y
tetX      tet with a mark on one face
cylO      cyl with a mark on its side, above
          mid-height
sphereX   sphere with a mark
========  ===========================================

The vertices of the polyhedra are orbits of scipy's groups, so their symmetry groups are exactly scipy's.

Marks
-----
A mark is a "comet": a disc of colour :data:`MARK_DISC_COLOUR` plus a smaller dot of
:data:`MARK_DOT_COLOUR` beside it, so that no rotation but the identity maps the mark onto itself.
Each part is the set of surface points within Euclidean distance ``rho`` of its centre (a point on
the surface), i.e. ball ``∩`` surface. Every part lies inside one smooth piece of the surface: on
tetX both parts lie on one face, away from the face centroid (so the 3-fold rotation about that face
moves them) and farther than ``rho`` from every other face plane; on cylO both lie on the side, above
mid-height (so the flips ``Ry @ Rx(180)`` move them) and farther than ``rho`` from the caps.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cache

import numpy as np
import torch

from image2sphere.checks import ConfigError
from image2sphere.so3.groups import rotation_group

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
    "exact_matmul3",
    "shape_geometry",
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
        raise ConfigError(f"shape must be one of {', '.join(SHAPES)}; got {shape!r}")
    return shape


def check_shape_list(shapes, key: str = "shapes") -> list[str]:
    """``shapes`` as a list, or ``ValueError`` naming ``key`` unless it is a non-empty sequence of distinct names."""
    if isinstance(shapes, str) or not isinstance(shapes, Sequence) or not shapes:
        raise ConfigError(f"{key} must be a non-empty sequence of names from {', '.join(SHAPES)}; got {shapes!r}")
    unknown = [s for s in shapes if s not in SHAPES]
    if unknown:
        raise ConfigError(f"{key}: unknown shape(s) {unknown}; valid shapes are {', '.join(SHAPES)}")
    if len(set(shapes)) != len(shapes):
        raise ConfigError(f"{key}: duplicate names in {list(shapes)}")
    return list(shapes)


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


def exact_matmul3(A: torch.Tensor, B: torch.Tensor) -> torch.Tensor:
    """``A @ B`` for broadcastable ``(..., 3, 3)`` stacks, as explicit sums (bit-identical for any batch)."""
    return (
        A[..., :, 0, None] * B[..., 0, None, :]
        + A[..., :, 1, None] * B[..., 1, None, :]
        + A[..., :, 2, None] * B[..., 2, None, :]
    )
