"""Pointwise nonlinearity on SO(3) signals (e3nn's ``SO3Activation``: to a grid, ReLU, back)."""

from __future__ import annotations

import copy

import torch
from e3nn.nn import SO3Activation
from e3nn.o3 import s2_grid
from torch import nn

from image2sphere.checks import check_int
from image2sphere.precision import constant_cache
from image2sphere.so3.wigner import check_lmax, default_dtype, flat_wigner_on_euler_grid

__all__ = ["SO3ReLU", "default_relu_resolution"]


@constant_cache(maxsize=8)
def _relu_on_grid(lmax: int, resolution: int, dtype: torch.dtype) -> SO3Activation:
    """e3nn's ReLU on its SO(3) grid, built once per process and setting, and shared by every layer and
    network of that setting. ``dtype``: the default dtype the grid is built in (part of the cache key).

    The module is e3nn's own (its grid's angles and quadrature weights, its normalised ReLU, its
    ``to_grid`` and ``from_grid``), built at degree 0; its Wigner matrices up to ``lmax`` come from
    :func:`flat_wigner_on_euler_grid` (the same numbers, from each angle's matrices: under a second where
    e3nn's constructor takes about 2.5 s of a CPU thread at lmax 6 and resolution 8 and over 20 s at lmax 10
    and resolution 12, for each of its two grids), and its input and output grids share one tensor (the
    same lmax and resolution: 374 MB once instead of twice at lmax 10 in float32, benchmarks/relu_grid.py)."""
    with default_dtype(dtype):
        act = SO3Activation(0, 0, torch.relu, resolution)
    grid = act.grid_in
    with default_dtype(torch.float64):  # the grid's angles at full precision (e3nn.o3.SO3Grid's formula)
        beta, alpha = s2_grid(grid.res_beta, grid.res_alpha)
    wigner = flat_wigner_on_euler_grid(lmax, alpha, beta, alpha, dtype=dtype)  # [alpha, beta, gamma, n_so3]
    for g in (act.grid_in, act.grid_out):
        if g.res_alpha != g.res_gamma or g.D.shape[:3] != wigner.shape[:3]:  # e3nn's layout, checked once
            raise RuntimeError(f"e3nn's SO3Grid changed its layout: {tuple(g.D.shape)}")
        g.register_buffer("D", wigner, persistent=False)
        for name, buf in list(g.named_buffers(recurse=False, remove_duplicate=False)):
            g.register_buffer(name, buf, persistent=False)  # constants: kept out of checkpoints
    act.lmax_in = act.lmax_out = lmax
    return act


def default_relu_resolution(lmax: int) -> int:
    """The ReLU grid's resolution for band limit ``lmax`` when none is given: ``max(8, lmax + 2)``."""
    return max(8, lmax + 2)


class SO3ReLU(nn.Module):
    """ReLU of an SO(3) signal ``[..., n_so3_coeffs(lmax)]`` evaluated on e3nn's SO(3) quadrature grid.

    Equivariant up to the grid's sampling error (smaller for larger ``resolution``). The grid's
    Wigner matrices are constants: they are kept out of checkpoints, and every layer of the same
    ``lmax`` and ``resolution`` in a process starts from the same tensors (``.to()`` gives each
    module its own copy, as for any buffer).

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
        shared = _relu_on_grid(self.lmax, self.resolution, torch.get_default_dtype())
        # a module of its own around the shared constant tensors (the memo maps each buffer to itself)
        self.act = copy.deepcopy(shared, memo={id(buf): buf for buf in shared.buffers()})

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x)
