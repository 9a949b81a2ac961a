"""Wigner D-matrices in the flat layout used for SO(3) signals.

Conventions (docs/conventions.md#flat-wigner-layout)
----------------------------------------------------
* ``D^l = e3nn.o3.wigner_D(l, alpha, beta, gamma)`` with YXY angles of the rotation, real basis.
* Flat layout: for ``l = 0..lmax`` the ``(2l+1)^2`` entries of a matrix ``c^l`` in row-major
  order ``(m, n)``, concatenated. A signal with coefficients ``c`` is
  ``f(R) = sum_l sqrt(2l+1) sum_{m,n} c^l[m,n] D^l(R)[m,n] = flat_wigner(lmax, R) @ c``.
* S2 signals: e3nn real spherical harmonics, ``normalization="component"``, ``(lmax+1)^2``
  coefficients ordered by l then m.
"""

from __future__ import annotations

import contextlib
import math

import torch
from e3nn import o3

from image2sphere.checks import ConfigError, check_int
from image2sphere.precision import constant_cache
from image2sphere.so3.rotations import check_rotation_matrix, matrix_to_angles

__all__ = [
    "check_lmax",
    "degree_scale",
    "flat_wigner",
    "flat_wigner_from_angles",
    "flat_wigner_on_euler_grid",
    "left_translate_so3_coeffs",
    "lmax_from_n_so3_coeffs",
    "n_s2_coeffs",
    "n_so3_coeffs",
    "rotate_s2_coeffs",
    "so3_blocks",
    "so3_layout",
    "wigner_D",
]


def check_lmax(lmax, name: str = "lmax") -> int:
    """Return ``lmax`` as an int, or raise ``ValueError`` (naming ``name``) if it is not an integer >= 0."""
    return check_int(name, lmax, 0)


def n_so3_coeffs(lmax: int) -> int:
    """Number of flat Wigner coefficients: ``sum_l (2l+1)^2 = (lmax+1)(2lmax+1)(2lmax+3)/3``."""
    lmax = check_lmax(lmax)
    return (lmax + 1) * (2 * lmax + 1) * (2 * lmax + 3) // 3


def n_s2_coeffs(lmax: int) -> int:
    """Number of real spherical-harmonic coefficients up to ``lmax``: ``(lmax+1)^2``."""
    return (check_lmax(lmax) + 1) ** 2


def lmax_from_n_so3_coeffs(n: int) -> int:
    """Inverse of :func:`n_so3_coeffs`; ``ValueError`` if ``n`` is not such a number."""
    check_int("the number of SO(3) coefficients", n, 1)
    lmax = 0
    while n_so3_coeffs(lmax) < n:
        lmax += 1
    if n_so3_coeffs(lmax) != n:
        raise ConfigError(f"{n} is not a valid number of SO(3) coefficients (455 for lmax 6, 165 for lmax 4)")
    return lmax


def so3_blocks(lmax: int) -> list[tuple[int, slice]]:
    """``(l, slice)`` of every band's ``(2l+1)^2`` entries in the flat Wigner layout."""
    blocks, offset = [], 0
    for l in range(check_lmax(lmax) + 1):
        blocks.append((l, slice(offset, offset + (2 * l + 1) ** 2)))
        offset += (2 * l + 1) ** 2
    return blocks


def so3_layout(lmax: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``(l, m, n)`` of every flat position, each a long tensor ``(n_so3_coeffs,)``.

    ``m`` and ``n`` are matrix indices in ``0..2l``, i.e. order ``-l..l`` shifted by ``l``.
    """
    return _so3_layout(check_lmax(lmax))


@constant_cache(maxsize=32)
def _so3_layout(lmax: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    ls, ms, ns = [], [], []
    for l in range(lmax + 1):
        idx = torch.arange(2 * l + 1)
        mm, nn_ = torch.meshgrid(idx, idx, indexing="ij")
        ls.append(torch.full(((2 * l + 1) ** 2,), l))
        ms.append(mm.reshape(-1))
        ns.append(nn_.reshape(-1))
    return torch.cat(ls), torch.cat(ms), torch.cat(ns)


def degree_scale(degrees: torch.Tensor, power, name: str = "degree_power") -> torch.Tensor:
    """``(2l+1)^-power`` (float32) for the degree ``l`` of each coefficient in ``degrees`` (e.g.
    ``so3_layout(lmax)[0]``); ``ValueError`` naming ``name`` unless ``power`` is a number >= 0."""
    if isinstance(power, bool) or not isinstance(power, (int, float)) or not power >= 0:
        raise ConfigError(f"{name} must be a number >= 0, got {power!r}")
    return ((2 * degrees.to(torch.float64) + 1) ** -float(power)).float()


@contextlib.contextmanager
def default_dtype(dtype: torch.dtype):
    """Temporarily set torch's default dtype.

    e3nn builds its Lie-algebra generators (hence ``wigner_D``) in the default dtype, so float64
    Wigner matrices are only float64-accurate when built under ``default_dtype(torch.float64)``.
    """
    previous = torch.get_default_dtype()
    torch.set_default_dtype(dtype)
    try:
        yield
    finally:
        torch.set_default_dtype(previous)


def wigner_D(l: int, alpha: torch.Tensor, beta: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
    """``e3nn.o3.wigner_D`` computed at the precision of ``alpha`` (float64 stays float64-accurate).

    ``l`` is a non-negative integer; the angles are tensors (or numbers) of broadcastable shapes
    ``(...)``; the result is ``(..., 2l+1, 2l+1)``.
    """
    l = check_lmax(l, "l")
    alpha, beta, gamma = (torch.as_tensor(a) for a in (alpha, beta, gamma))
    alpha, beta, gamma = (a if a.is_floating_point() else a.to(torch.get_default_dtype()) for a in (alpha, beta, gamma))
    dtype = torch.promote_types(alpha.dtype, torch.float32)
    with default_dtype(torch.float64 if dtype == torch.float64 else torch.get_default_dtype()):
        return o3.wigner_D(l, alpha, beta, gamma).to(dtype)


def flat_wigner_from_angles(lmax: int, alpha: torch.Tensor, beta: torch.Tensor, gamma: torch.Tensor) -> torch.Tensor:
    """``sqrt(2l+1) D^l(alpha, beta, gamma)`` flattened and concatenated: ``(..., n_so3_coeffs)``."""
    lmax = check_lmax(lmax)
    alpha, beta, gamma = torch.broadcast_tensors(alpha, beta, gamma)
    blocks = [
        math.sqrt(2 * l + 1) * wigner_D(l, alpha, beta, gamma).flatten(-2)  # [..., (2l+1)^2]
        for l in range(lmax + 1)
    ]
    return torch.cat(blocks, dim=-1)


def flat_wigner_on_euler_grid(
    lmax: int, alpha: torch.Tensor, beta: torch.Tensor, gamma: torch.Tensor, dtype: torch.dtype | None = None
) -> torch.Tensor:
    """:func:`flat_wigner_from_angles` on the product grid ``alpha x beta x gamma``: ``[A, B, C, n_so3_coeffs]``,
    entry ``[a, b, c]`` being that of the angles ``(alpha[a], beta[b], gamma[c])`` (the layout of e3nn's
    ``SO3Grid.D``).

    Built from each angle's own matrices, ``D(alpha, beta, gamma) = D(alpha, 0, 0) D(0, beta, 0) D(0, 0, gamma)``
    (the YXY angles compose, as e3nn defines them): ``(2l+1)^3`` products per grid point and degree, in float64,
    instead of e3nn's matrix exponential at every point (``SO3Grid`` takes tens of seconds of a CPU thread at
    lmax 10). ``alpha``, ``beta``, ``gamma``: 1-D; ``dtype``: of the result (default: the angles', at least
    float32).
    """
    lmax = check_lmax(lmax)
    for name, angles in (("alpha", alpha), ("beta", beta), ("gamma", gamma)):
        if angles.ndim != 1:
            raise ConfigError(f"{name} must have shape (n,), got {tuple(angles.shape)}")
    dtype = torch.promote_types(alpha.dtype, torch.float32) if dtype is None else dtype
    alpha, beta, gamma = (a.to(torch.float64) for a in (alpha, beta, gamma))
    zero = torch.zeros((), dtype=torch.float64, device=alpha.device)
    out = torch.empty(len(alpha), len(beta), len(gamma), n_so3_coeffs(lmax), dtype=dtype, device=alpha.device)
    for l, block in so3_blocks(lmax):
        Da = wigner_D(l, alpha, zero, zero)  # [A, d, d]
        Db = wigner_D(l, zero, beta, zero)  # [B, d, d]
        Dg = wigner_D(l, zero, zero, gamma)  # [C, d, d]
        Dab = torch.einsum("aij,bjk->abik", Da, Db)  # [A, B, d, d]
        Dg = math.sqrt(2 * l + 1) * Dg
        for a in range(len(alpha)):  # one alpha at a time: [B, C, d, d] in float64 at most
            out[a, ..., block] = torch.einsum("bik,ckm->bcim", Dab[a], Dg).flatten(-2)  # [B, C, d^2]
    return out


def flat_wigner(lmax: int, rotations: torch.Tensor) -> torch.Tensor:
    """Flat Wigner layout of rotations ``(..., 3, 3)`` -> ``(..., n_so3_coeffs)``.

    ``flat_wigner(lmax, R) @ c`` evaluates the SO(3) signal with coefficients ``c`` at ``R``.
    """
    lmax = check_lmax(lmax)
    check_rotation_matrix(rotations)
    return flat_wigner_from_angles(lmax, *matrix_to_angles(rotations))


def _wigner_blocks(lmax: int, rotation: torch.Tensor) -> list[torch.Tensor]:
    check_rotation_matrix(rotation)
    if rotation.shape != (3, 3):
        raise ConfigError(f"rotation must have shape (3, 3), got {tuple(rotation.shape)}")
    angles = matrix_to_angles(rotation)
    return [wigner_D(l, *angles) for l in range(check_lmax(lmax) + 1)]


def rotate_s2_coeffs(x: torch.Tensor, rotation: torch.Tensor, lmax: int) -> torch.Tensor:
    """Coefficients ``(..., (lmax+1)^2)`` of the rotated S2 signal ``x(R^-1 u)``: ``x^l -> D^l(R) x^l``."""
    if x.shape[-1] != n_s2_coeffs(lmax):
        raise ConfigError(f"S2 coefficients must end in {n_s2_coeffs(lmax)} for lmax={lmax}, got {tuple(x.shape)}")
    blocks = _wigner_blocks(lmax, rotation.to(x.dtype))
    out = [x[..., l * l : (l + 1) ** 2] @ D.T for l, D in enumerate(blocks)]  # D x per l  [..., 2l+1]
    return torch.cat(out, dim=-1)


def left_translate_so3_coeffs(c: torch.Tensor, rotation: torch.Tensor, lmax: int) -> torch.Tensor:
    """Coefficients ``(..., n_so3_coeffs)`` of the left-translated signal ``f(R^-1 g)``: ``c^l -> D^l(R) c^l``."""
    if c.shape[-1] != n_so3_coeffs(lmax):
        raise ConfigError(f"SO(3) coefficients must end in {n_so3_coeffs(lmax)} for lmax={lmax}, got {tuple(c.shape)}")
    Ds = _wigner_blocks(lmax, rotation.to(c.dtype))
    out = []
    for (l, block), D in zip(so3_blocks(lmax), Ds, strict=True):
        C = c[..., block].unflatten(-1, (2 * l + 1, 2 * l + 1))  # [..., d, d]
        out.append((D @ C).flatten(-2))
    return torch.cat(out, dim=-1)
