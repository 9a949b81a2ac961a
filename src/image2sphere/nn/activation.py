"""Pointwise nonlinearity on SO(3) signals (e3nn's ``SO3Activation``: to a grid, ReLU, back)."""

from __future__ import annotations

import torch
from e3nn.nn import SO3Activation
from torch import nn

from image2sphere.so3.wigner import check_lmax

__all__ = ["SO3ReLU"]


class SO3ReLU(nn.Module):
    """ReLU of an SO(3) signal ``[..., n_so3_coeffs(lmax)]`` evaluated on e3nn's SO(3) quadrature grid.

    Equivariant up to the grid's sampling error (smaller for larger ``resolution``). The grid's
    Wigner matrices are constants: they are kept out of checkpoints.
    """

    def __init__(self, lmax: int = 6, resolution: int = 8):
        super().__init__()
        self.lmax = check_lmax(lmax)
        if resolution < 1:
            raise ValueError(f"resolution must be >= 1, got {resolution!r}")
        self.act = SO3Activation(lmax, lmax, torch.relu, resolution)
        for grid in (self.act.grid_in, self.act.grid_out):
            for name, buf in list(grid.named_buffers(recurse=False, remove_duplicate=False)):
                grid.register_buffer(name, buf, persistent=False)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.act(x)
