"""S2 -> SO(3) group convolution with a globally supported filter, in the Fourier domain.

Conventions
-----------
Input: S2 coefficients ``x[b, f, (l, m)]`` (real SH, component normalisation, ``(lmax+1)^2``).
Filter: S2 coefficients ``psi[f, g, (l, n)]``. Output: SO(3) coefficients in the flat Wigner
layout (:mod:`image2sphere.so3.wigner`) with

    out^l[b, g][m, n] = sum_f x^l[b, f, m] * psi^l[f, g, n] / sqrt(f_in)

so that ``out_g(R) = sum_f sum_l sqrt(2l+1) x_f^l . (D^l(R) psi_fg^l) / sqrt(f_in)``: the group
convolution ``(x * psi)(R) = <x, psi(R^-1 .)>`` with each band of the filter scaled by sqrt(2l+1)
(a reparametrisation of the learned filter). Rotating the input by ``Q`` (``x^l -> D^l(Q) x^l``)
left-translates the output: ``out'(R) = out(Q^-1 R)``.
"""

from __future__ import annotations

import math

import torch
from e3nn import o3
from torch import nn

from image2sphere.so3.grid import s2_healpix_grid
from image2sphere.so3.wigner import check_lmax, n_s2_coeffs, so3_layout

__all__ = ["S2Conv"]

FILTERS = ("harmonic", "spatial")


class S2Conv(nn.Module):
    """S2 convolution ``[B, f_in, (lmax+1)^2] -> [B, f_out, n_so3_coeffs(lmax)]``.

    Args:
        filter: ``"harmonic"``: the filter's SH coefficients are the parameters (I2S default);
            ``"spatial"``: the filter is a weighted sum of point masses on the HEALPix grid of
            ``kernel_level`` restricted to ``beta <= kernel_max_beta`` (global support by default).
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        lmax: int = 6,
        filter: str = "harmonic",
        kernel_level: int = 2,
        kernel_max_beta: float = math.pi,
    ):
        super().__init__()
        self.lmax = check_lmax(lmax)
        if filter not in FILTERS:
            raise ValueError(f"filter must be one of {FILTERS}, got {filter!r}")
        self.filter_kind = filter
        self.in_channels, self.out_channels = in_channels, out_channels
        if filter == "harmonic":
            self.weight = nn.Parameter(torch.randn(in_channels, out_channels, n_s2_coeffs(lmax)))
        else:
            alpha, beta = s2_healpix_grid(kernel_level, max_beta=kernel_max_beta, dtype=torch.float64)
            Y = o3.spherical_harmonics_alpha_beta(list(range(lmax + 1)), alpha, beta, normalization="component")
            self.register_buffer("kernel_Y", Y.float() / math.sqrt(len(alpha)), persistent=False)  # [K, (L+1)^2]
            self.weight = nn.Parameter(torch.randn(in_channels, out_channels, len(alpha)))
        l_of, m_of, n_of = so3_layout(lmax)
        self.register_buffer("index_x", l_of**2 + m_of, persistent=False)  # [n_so3] -> S2 index of m
        self.register_buffer("index_psi", l_of**2 + n_of, persistent=False)  # [n_so3] -> S2 index of n

    def filter(self) -> torch.Tensor:
        """The filter's S2 coefficients ``[f_in, f_out, (lmax+1)^2]``."""
        if self.filter_kind == "harmonic":
            return self.weight
        return torch.einsum("fgk,kj->fgj", self.weight, self.kernel_Y)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = n_s2_coeffs(self.lmax)
        if x.ndim != 3 or x.shape[1:] != (self.in_channels, n):
            raise ValueError(f"S2 input must have shape (batch, {self.in_channels}, {n}), got {tuple(x.shape)}")
        xs = x[..., self.index_x]  # [B, f_in, n_so3]
        ps = self.filter()[..., self.index_psi]  # [f_in, f_out, n_so3]
        return torch.einsum("bfi,fgi->bgi", xs, ps) / math.sqrt(self.in_channels)  # [B, f_out, n_so3]
