"""Pointwise nonlinearity on SO(3) signals: e3nn's ``SO3Activation`` (to its grid, ReLU, back), computed with
its grid's Wigner matrices in the grid's real Fourier basis of alpha and gamma.

Conventions
-----------
* Signals: the flat Wigner layout (``image2sphere.so3.wigner``), ``[..., n]`` with ``n = n_so3_coeffs(lmax)``.
* The grid: e3nn's ``SO3Grid(lmax, resolution)``, ``A = 4 r`` alphas and gammas (the same angles), ``B = 2 r``
  betas with e3nn's quadrature weights; in this module laid out ``[..., B, C, A]`` (e3nn: ``[..., A, B, C]``).
* ``M``: the number of real Fourier functions of alpha (and gamma) kept, ``2 lmax + 1`` on a grid fine enough
  for lmax (``A > 2 lmax``), every function of the ``A`` angles on a coarser one.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import torch
from e3nn.nn import SO3Activation
from e3nn.o3 import s2_grid
from torch import nn

from image2sphere.checks import ConfigError, check_int
from image2sphere.precision import constant_cache, float32_region
from image2sphere.so3.wigner import check_lmax, default_dtype, n_so3_coeffs, so3_blocks, wigner_D

__all__ = ["SO3ReLU", "default_relu_resolution"]


class _Grid(NamedTuple):
    """The ReLU's grid as a separable operator (see :class:`SO3ReLU`)."""

    indices: torch.Tensor  # [2, nnz]: the nonzero entries (i, (b, p, q)) of K, the Wigner matrices in the basis
    values: torch.Tensor  # [nnz]: K[i, b, p, q] (1 in 200 entries at lmax 10: D_i has frequencies m_i and n_i only)
    fourier: torch.Tensor  # [A, M]: the M real Fourier functions of alpha (and of gamma) at the grid's A angles
    weights: torch.Tensor  # [B]: e3nn's quadrature weights of the beta rings
    act: nn.Module  # e3nn's ReLU, normalised to keep the second moment


def _real_fourier(angles: torch.Tensor, lmax: int) -> torch.Tensor:
    """``[A, M]``: ``1, cos(k t), sin(k t)`` for ``k = 1..K`` at the angles, ``K = min(lmax, (A - 1) // 2)``, and
    ``cos(A t / 2)`` if ``A`` is even and ``A / 2 <= lmax``: every frequency of degrees up to lmax as the
    ``A`` equally spaced angles see it (all of them, aliased, on a grid too coarse for lmax)."""
    n = len(angles)
    top = min(lmax, (n - 1) // 2)
    k = torch.arange(1, top + 1, dtype=angles.dtype)
    columns = [torch.ones_like(angles)[:, None], torch.cos(angles[:, None] * k), torch.sin(angles[:, None] * k)]
    if n % 2 == 0 and n // 2 <= lmax:
        columns.append(torch.cos(angles * (n // 2))[:, None])
    return torch.cat(columns, dim=1)


@constant_cache(maxsize=8)
def _relu_grid(lmax: int, resolution: int, dtype: torch.dtype) -> _Grid:
    """e3nn's SO(3) grid of ``SO3Activation(lmax, lmax, relu, resolution)`` as a separable operator, built
    once per process and setting and shared by every layer and network. ``dtype``: the default dtype the
    grid is built in (part of the cache key).

    e3nn evaluates ``f(a, b, c) = sum_i x_i D_i(alpha_a, beta_b, gamma_c)`` with the dense ``[A, B, C, n]``
    Wigner matrices of its grid. Each matrix is, in alpha and in gamma, a real Fourier series of degree at
    most lmax: ``D_i(alpha_a, beta_b, gamma_c) = sum_pq F[a, p] K[i, b, p, q] F[c, q]``, exactly on the grid.
    ``K`` comes from each angle's own Wigner matrices, ``D(alpha, beta, gamma) = D(alpha, 0, 0) D(0, beta, 0)
    D(0, 0, gamma)``, projected on the Fourier functions ``F`` (their pseudo-inverse, in float64)."""
    with default_dtype(dtype):
        e3nn = SO3Activation(0, 0, torch.relu, resolution)  # its grid's size and weights, its normalised ReLU
    grid = e3nn.grid_in
    if grid.res_alpha != grid.res_gamma:  # e3nn's layout, relied on below
        raise RuntimeError(f"e3nn's SO3Grid changed its layout: {grid.res_alpha} alphas, {grid.res_gamma} gammas")
    with default_dtype(torch.float64):  # the grid's angles at full precision (e3nn.o3.SO3Grid's formula)
        beta, alpha = s2_grid(grid.res_beta, grid.res_alpha)
    fourier = _real_fourier(alpha, lmax)  # [A, M]
    project = torch.linalg.pinv(fourier)  # [M, A]
    zero = torch.zeros((), dtype=torch.float64)
    blocks = []
    for l, _ in so3_blocks(lmax):
        Da = project @ wigner_D(l, alpha, zero, zero).flatten(1)  # [M, d * d]: D(alpha, 0, 0) in the basis
        Da = Da.unflatten(1, (2 * l + 1, 2 * l + 1))  # [M(p), d(i), d(k)]
        Dg = torch.einsum("qc,cmj->qmj", project, wigner_D(l, zero, zero, alpha))  # [M(q), d(m), d(j)]
        Db = wigner_D(l, zero, beta, zero)  # [B, d(k), d(m)]
        K = torch.einsum("pik,bkm,qmj->ijbpq", Da, Db, Dg) * math.sqrt(2 * l + 1)  # [d, d, B, M, M]
        blocks.append(K.flatten(0, 1).flatten(1))  # [d * d, B * M * M]
    K = torch.cat(blocks)  # [n, B * M * M]
    K = torch.where(K.abs() > 1e-10 * K.abs().max(), K, 0)  # rounding left where the exact value is 0
    indices = K.nonzero().T  # [2, nnz]
    return _Grid(indices, K[indices[0], indices[1]].to(dtype), fourier.to(dtype), grid.qw.to(dtype), e3nn.act)


def default_relu_resolution(lmax: int) -> int:
    """The ReLU grid's resolution for band limit ``lmax`` when none is given: ``max(8, lmax + 2)``."""
    return max(8, lmax + 2)


class SO3ReLU(nn.Module):
    """ReLU of an SO(3) signal ``[..., n_so3_coeffs(lmax)]`` evaluated on e3nn's SO(3) quadrature grid.

    Equivariant up to the grid's sampling error (smaller for larger ``resolution``). The same numbers as
    e3nn's ``SO3Activation(lmax, lmax, relu, resolution)`` (to rounding), from a sparse operator instead of
    its dense matrices (see :func:`_relu_grid`). The grid's tensors are constants: they are kept out of
    checkpoints, and every layer of the same ``lmax`` and ``resolution`` in a process starts from the same
    tensors (``.to()`` gives each module its own copy, as for any buffer). Its forward pass computes in
    float32 under autocast.

    ``resolution``: e3nn's grid resolution ``r`` (``32 r^3`` rotations); the finer the grid, the less
    the ReLU's output, which has every degree, aliases into degrees up to lmax. ``None`` (the
    default) follows the band limit: ``max(8, lmax + 2)``, one degree to spare above lmax and never
    coarser than lmax 6's grid (a finer grid only lowers the aliasing, and below lmax 6 it costs
    little). A grid fixed at 8 is one degree short at lmax 8 and three at lmax 10, and it cost those
    band limits up to 0.8 nats after 2 epochs on the built-in data (docs/training_fidelity.md,
    "The ReLU's grid").
    """

    def __init__(self, lmax: int = 6, resolution: int | None = None):
        super().__init__()
        self.lmax = check_lmax(lmax)
        resolution = check_int("resolution", resolution, 1, allow_none=True, note=" (max(8, lmax + 2))")
        self.resolution = default_relu_resolution(self.lmax) if resolution is None else resolution
        grid = _relu_grid(self.lmax, self.resolution, torch.get_default_dtype())
        self.register_buffer("indices", grid.indices, persistent=False)  # [2, nnz]
        self.register_buffer("values", grid.values, persistent=False)  # [nnz]
        self.register_buffer("fourier", grid.fourier, persistent=False)  # [A, M]
        self.register_buffer("weights", grid.weights, persistent=False)  # [B]
        self.act = grid.act
        self.n = n_so3_coeffs(self.lmax)

    def wigner(self) -> torch.Tensor:
        """``K`` as a sparse ``[n, B * M * M]`` matrix."""
        M = self.fourier.shape[1]
        size = (self.n, len(self.weights) * M * M)
        return torch.sparse_coo_tensor(self.indices, self.values, size, is_coalesced=True, check_invariants=False)

    def to_grid(self, x: torch.Tensor) -> torch.Tensor:
        """``[..., n]`` -> ``[..., B, C, A]``: e3nn's ``SO3Grid.to_grid`` (its ``[..., A, B, C]``, beta first and
        alpha last)."""
        M = self.fourier.shape[1]
        y = torch.sparse.mm(self.wigner().t(), x.reshape(-1, self.n).T).T  # [N, B * M * M]
        y = y.reshape(*x.shape[:-1], -1, M, M)  # [..., B, M(p), M(q)]
        f = (y @ self.fourier.T).transpose(-1, -2) @ self.fourier.T  # [..., B, C, A]
        return f / math.sqrt(self.n)

    def from_grid(self, f: torch.Tensor) -> torch.Tensor:
        """``[..., B, C, A]`` -> ``[..., n]``: e3nn's ``SO3Grid.from_grid`` (quadrature over the grid)."""
        g = (f @ self.fourier).transpose(-1, -2) @ self.fourier  # [..., B, M(p), M(q)]
        g = (g * self.weights[:, None, None]).flatten(-3)  # [..., B * M * M]
        out = torch.sparse.mm(self.wigner(), g.reshape(-1, g.shape[-1]).T).T  # [N, n]
        return out.reshape(*f.shape[:-3], self.n) * math.sqrt(self.n)

    @float32_region
    def forward(self, x: torch.Tensor) -> torch.Tensor:
        if x.shape[-1] != self.n:
            raise ConfigError(
                f"SO(3) signal must have shape (..., {self.n}) for lmax {self.lmax}, got {tuple(x.shape)}"
            )
        return self.from_grid(self.act(self.to_grid(x)))
