"""Rotation helpers.

Conventions (project-wide, see docs/conventions.md#rotation-matrices)
---------------------------------------------------------------------
* Rotation matrices have shape ``(..., 3, 3)``, act on column vectors: ``x_camera = R @ x_object``.
* Euler angles are e3nn's Y-X-Y convention: ``R = Ry(alpha) @ Rx(beta) @ Ry(gamma)`` with
  ``alpha, gamma`` in ``[0, 2 pi)`` (or ``(-pi, pi]``) and ``beta`` in ``[0, pi]``.
* Quaternions are unit quaternions; the scalar position is given explicitly by ``order``:
  ``"wxyz"`` (scalar first, e.g. ModelNet10-SO(3)'s ``viewID2quat.pkl``) or ``"xyzw"``
  (scalar last, as in scipy).
* Geodesic angles are in radians unless a name says ``_deg``.
"""

from __future__ import annotations

import math

import torch
from e3nn import o3

__all__ = [
    "angles_to_matrix",
    "check_rotation_matrix",
    "geodesic_distance",
    "geodesic_distance_deg",
    "matrix_to_angles",
    "project_to_so3",
    "quaternion_to_matrix",
    "random_rotations",
    "rotvec_to_matrix",
]


def check_rotation_matrix(R: torch.Tensor, name: str = "rotation", atol: float = 1e-4) -> torch.Tensor:
    """Raise ``ValueError`` unless ``R`` is a stack of proper rotations ``(..., 3, 3)``.

    ``atol`` bounds ``max |R^T R - I|`` and ``|det R - 1|``. Returns ``R`` unchanged.
    """
    if not isinstance(R, torch.Tensor):
        raise ValueError(f"{name} must be a torch.Tensor of shape (..., 3, 3), got {type(R).__name__}")
    if R.ndim < 2 or R.shape[-2:] != (3, 3):
        raise ValueError(f"{name} must have shape (..., 3, 3), got {tuple(R.shape)}")
    if not R.is_floating_point():
        raise ValueError(f"{name} must be a floating point tensor, got {R.dtype}")
    if R.numel() == 0:
        return R
    with torch.no_grad():
        Rd = R.detach().to(torch.float64)
        eye = torch.eye(3, dtype=torch.float64, device=R.device)
        ortho_err = (Rd.transpose(-1, -2) @ Rd - eye).abs().amax()
        det_err = (torch.linalg.det(Rd) - 1).abs().amax()
        if not torch.isfinite(ortho_err) or ortho_err > atol or det_err > atol:
            raise ValueError(
                f"{name} is not a rotation matrix: max |R^T R - I| = {ortho_err.item():.3g}, "
                f"max |det R - 1| = {det_err.item():.3g} (tolerance {atol:g}). "
                "Use image2sphere.so3.project_to_so3 to orthonormalise near-rotations."
            )
    return R


def angles_to_matrix(alpha: torch.Tensor, beta: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
    """YXY Euler angles ``(...)`` -> rotation matrices ``(..., 3, 3)`` (e3nn convention)."""
    return o3.angles_to_matrix(alpha, beta, gamma)


def matrix_to_angles(R: torch.Tensor, atol: float = 1e-4) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Rotation matrices ``(..., 3, 3)`` -> YXY Euler angles ``(alpha, beta, gamma)``, each ``(...)``.

    ``alpha, gamma`` lie in ``(-pi, pi]``, ``beta`` in ``[0, pi]``. Raises ``ValueError`` for
    non-rotations. At ``beta = 0`` or ``pi`` only ``alpha +- gamma`` is determined.
    """
    check_rotation_matrix(R, atol=atol)
    # Same construction as e3nn.o3.matrix_to_angles, without its exact det(R) == 1 assertion
    # (float32 data fails it) and with a gradient-safe acos.
    y = R[..., :, 1]  # R @ e_y  [..., 3]
    alpha = torch.atan2(y[..., 0], y[..., 2])
    beta = _acos(y[..., 1] / torch.linalg.vector_norm(y, dim=-1))
    R0 = o3.angles_to_matrix(alpha, beta, torch.zeros_like(alpha))
    rest = R0.transpose(-1, -2) @ R  # = Ry(gamma)
    gamma = torch.atan2(rest[..., 0, 2], rest[..., 0, 0])
    return alpha, beta, gamma


def quaternion_to_matrix(q: torch.Tensor, order: str) -> torch.Tensor:
    """Unit quaternions ``(..., 4)`` -> rotation matrices ``(..., 3, 3)``.

    ``order`` is ``"wxyz"`` (scalar first) or ``"xyzw"`` (scalar last); there is no default,
    because guessing it silently gives wrong labels. Quaternions are normalised; ``q`` and ``-q``
    give the same matrix.
    """
    if order not in ("wxyz", "xyzw"):
        raise ValueError(f"order must be 'wxyz' or 'xyzw', got {order!r}")
    if q.ndim < 1 or q.shape[-1] != 4:
        raise ValueError(f"quaternions must have shape (..., 4), got {tuple(q.shape)}")
    if not q.is_floating_point():
        raise ValueError(f"quaternions must be a floating point tensor, got {q.dtype}")
    norm = torch.linalg.vector_norm(q, dim=-1, keepdim=True)
    if (norm < 1e-8).any() or not torch.isfinite(norm).all():
        raise ValueError("quaternions must be finite and non-zero")
    q = q / norm
    if order == "wxyz":
        w, x, y, z = q.unbind(-1)
    else:
        x, y, z, w = q.unbind(-1)
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
        [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
        [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)],
    ]
    return torch.stack([torch.stack(r, dim=-1) for r in rows], dim=-2)


class _ClampedAcos(torch.autograd.Function):
    """``acos(clamp(x, -1, 1))`` whose gradient stays finite at ``x = +-1``.

    The value is exact; the derivative ``-1 / sqrt(1 - x^2)`` uses ``max(1 - x^2, eps)``.
    """

    @staticmethod
    def forward(ctx, x):
        ctx.save_for_backward(x)
        return torch.acos(x.clamp(-1.0, 1.0))

    @staticmethod
    def backward(ctx, grad):
        (x,) = ctx.saved_tensors
        eps = torch.finfo(x.dtype).eps
        denom = torch.sqrt((1 - x.clamp(-1.0, 1.0) ** 2).clamp_min(eps))
        return -grad / denom


def _acos(x: torch.Tensor) -> torch.Tensor:
    return _ClampedAcos.apply(x)


def geodesic_distance(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """Angle of ``R1^T R2`` in radians, ``(...)`` for broadcastable ``(..., 3, 3)`` inputs.

    ``arccos(clamp((trace(R1^T R2) - 1) / 2, -1, 1))`` with a gradient that stays finite at
    0 and pi.
    """
    for name, R in (("R1", R1), ("R2", R2)):
        if R.ndim < 2 or R.shape[-2:] != (3, 3):
            raise ValueError(f"{name} must have shape (..., 3, 3), got {tuple(R.shape)}")
    trace = (R1 * R2).sum(dim=(-1, -2))  # trace(R1^T R2)  [...]
    return _acos((trace - 1) / 2)


def project_to_so3(M: torch.Tensor) -> torch.Tensor:
    """Closest rotation (Frobenius norm) to each ``(..., 3, 3)`` matrix, via SVD.

    ``U diag(1, 1, det(U V^T)) V^T``: the special orthogonal Procrustes solution.
    """
    if M.ndim < 2 or M.shape[-2:] != (3, 3):
        raise ValueError(f"matrices must have shape (..., 3, 3), got {tuple(M.shape)}")
    U, _, Vh = torch.linalg.svd(M)
    d = torch.linalg.det(U @ Vh)  # [...]
    ones = torch.ones_like(d)
    S = torch.diag_embed(torch.stack([ones, ones, d], dim=-1))
    return U @ S @ Vh


def random_rotations(
    n: int,
    *,
    generator: torch.Generator | None = None,
    dtype: torch.dtype | None = None,
    device: torch.device | str | None = None,
) -> torch.Tensor:
    """``n`` rotations ``(n, 3, 3)`` drawn from the uniform (Haar) distribution.

    Normalised Gaussian quaternions are uniform on S^3, hence Haar-distributed rotations.
    """
    if n < 0:
        raise ValueError(f"n must be >= 0, got {n}")
    q = torch.randn(n, 4, generator=generator, dtype=dtype or torch.get_default_dtype(), device=device)
    return quaternion_to_matrix(q, order="wxyz")


def geodesic_distance_deg(R1: torch.Tensor, R2: torch.Tensor) -> torch.Tensor:
    """:func:`geodesic_distance` in degrees."""
    return geodesic_distance(R1, R2) * (180.0 / math.pi)


def rotvec_to_matrix(rotvec: torch.Tensor) -> torch.Tensor:
    """Axis-angle vectors ``(..., 3)`` (axis times angle in radians) -> rotations ``(..., 3, 3)``.

    The matrix exponential of the skew-symmetric matrix; differentiable everywhere, including 0.
    """
    if rotvec.ndim < 1 or rotvec.shape[-1] != 3:
        raise ValueError(f"rotation vectors must have shape (..., 3), got {tuple(rotvec.shape)}")
    x, y, z = rotvec.unbind(-1)
    zero = torch.zeros_like(x)
    skew = torch.stack(  # [..., 3, 3]
        [torch.stack([zero, -z, y], -1), torch.stack([z, zero, -x], -1), torch.stack([-y, x, zero], -1)], -2
    )
    return torch.linalg.matrix_exp(skew)
