"""S2 -> SO(3) group convolution with a globally supported filter, in the Fourier domain.

Conventions
-----------
Input: S2 coefficients ``x[b, f, (l, m)]`` (real SH, component normalisation, ``(lmax+1)^2``).
Filter: S2 coefficients ``psi[f, g, (l, n)]``. Output: SO(3) coefficients in the flat Wigner
layout (:mod:`image2sphere.so3.wigner`) with

    out^l[b, g][m, n] = sum_f x^l[b, f, m] * psi^l[f, g, n] * scale

so that ``out_g(R) = sum_f sum_l sqrt(2l+1) x_f^l . (D^l(R) psi_fg^l) * scale``: the group
convolution ``(x * psi)(R) = <x, psi(R^-1 .)>`` with each band of the filter scaled by sqrt(2l+1)
(a reparametrisation of the learned filter). Rotating the input by ``Q`` (``x^l -> D^l(Q) x^l``)
left-translates the output: ``out'(R) = out(Q^-1 R)``.

Initialisation (``init``): ``"unit"`` (default) draws ``psi ~ N(0, 1)`` and uses
``scale = 1 / sqrt(f_in)``. ``"fan_in"`` draws the filter at the scale that keeps the signal's mean
square, ``psi ~ N(0, g^2 / f_in)`` with ``g^2 = sum_l (2l+1) / sum_l (2l+1)^2`` (for an input whose
power is spread over the bands like white noise), and ``scale = 1``: the parameters are the filter
itself, as in ``nn.Linear``. Its output is ``g`` (about 1/3 at lmax 6) times the other's, and with
Adam (steps of a fixed size in the parameters) its filter moves ``sqrt(f_in) / g`` times faster
relative to its size. Both start close to uniform's loss once the projection is a mean over its
points; on the built-in data ``"fan_in"`` never learned the cube (docs/training_fidelity.md).
``"kaiming_uniform"`` is the original research code's draw: ``torch.nn.init.kaiming_uniform_`` with
its default arguments on the ``[f_in, f_out, n]`` weight tensor (``n = (lmax+1)^2`` coefficients, or
``K`` grid points for the spatial filter), i.e. ``U(-b, b)`` with ``b = sqrt(6 / (f_out * n))`` and
standard deviation ``sqrt(2 / (f_out * n))`` (0.071 at f_out 8, lmax 6): torch reads dimension 1,
``f_out``, as the fan-in of a tensor laid out this way. The forward scale is ``1 / sqrt(f_in)``, as
``"unit"``'s (e3nn's ``o3.Linear`` path normalisation in the original). Its SO(3) convolutions draw as
``"unit"`` does (:mod:`image2sphere.nn.so3_conv`).
"""

from __future__ import annotations

import math

import torch
from e3nn import o3
from torch import nn

from image2sphere.checks import ConfigError
from image2sphere.so3.grid import s2_healpix_grid
from image2sphere.so3.wigner import check_lmax, n_s2_coeffs, so3_layout

__all__ = ["S2Conv"]

FILTERS = ("harmonic", "spatial")
INITS = ("fan_in", "kaiming_uniform", "unit")


class S2Conv(nn.Module):
    """S2 convolution ``[B, f_in, (lmax+1)^2] -> [B, f_out, n_so3_coeffs(lmax)]``.

    Args:
        filter: ``"harmonic"``: the filter's SH coefficients are the parameters (I2S default);
            ``"spatial"``: the filter is a weighted sum of point masses on the HEALPix grid of
            ``kernel_level`` restricted to ``beta <= kernel_max_beta`` (global support by default).
        init: ``"unit"``, ``"fan_in"`` or ``"kaiming_uniform"``, see the module docstring.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        lmax: int = 6,
        filter: str = "harmonic",
        kernel_level: int = 2,
        kernel_max_beta: float = math.pi,
        init: str = "unit",
    ):
        super().__init__()
        self.lmax = check_lmax(lmax)
        if filter not in FILTERS:
            raise ConfigError(f"filter must be one of {FILTERS}, got {filter!r}")
        if init not in INITS:
            raise ConfigError(f"init must be one of {INITS}, got {init!r}")
        self.filter_kind = filter
        self.init = init
        self.in_channels, self.out_channels = in_channels, out_channels
        degrees = torch.arange(lmax + 1, dtype=torch.float64)
        gain = math.sqrt(float((2 * degrees + 1).sum() / ((2 * degrees + 1) ** 2).sum()))
        std = gain / math.sqrt(in_channels) if init == "fan_in" else 1.0
        self.scale = 1.0 if init == "fan_in" else 1 / math.sqrt(in_channels)
        if filter == "harmonic":
            self.weight = nn.Parameter(self._draw(in_channels, out_channels, n_s2_coeffs(lmax), std))
        else:
            alpha, beta = s2_healpix_grid(kernel_level, max_beta=kernel_max_beta, dtype=torch.float64)
            Y = o3.spherical_harmonics_alpha_beta(list(range(lmax + 1)), alpha, beta, normalization="component")
            # point masses weighted by 1/sqrt(K): each filter coefficient has about the weights' variance
            self.register_buffer("kernel_Y", Y.float() / math.sqrt(len(alpha)), persistent=False)  # [K, (L+1)^2]
            self.weight = nn.Parameter(self._draw(in_channels, out_channels, len(alpha), std))
        l_of, m_of, n_of = so3_layout(lmax)
        self.register_buffer("index_x", l_of**2 + m_of, persistent=False)  # [n_so3] -> S2 index of m
        self.register_buffer("index_psi", l_of**2 + n_of, persistent=False)  # [n_so3] -> S2 index of n

    def _draw(self, f_in: int, f_out: int, n: int, std: float) -> torch.Tensor:
        """Initial weights ``[f_in, f_out, n]``: ``kaiming_uniform_``'s draw under ``"kaiming_uniform"``,
        else ``N(0, std^2)``."""
        if self.init == "kaiming_uniform":
            return nn.init.kaiming_uniform_(torch.empty(f_in, f_out, n))
        return torch.randn(f_in, f_out, n) * std

    def filter(self) -> torch.Tensor:
        """The filter's S2 coefficients ``[f_in, f_out, (lmax+1)^2]``."""
        if self.filter_kind == "harmonic":
            return self.weight
        return torch.einsum("fgk,kj->fgj", self.weight, self.kernel_Y)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = n_s2_coeffs(self.lmax)
        if x.ndim != 3 or x.shape[1:] != (self.in_channels, n):
            raise ConfigError(f"S2 input must have shape (batch, {self.in_channels}, {n}), got {tuple(x.shape)}")
        xs = x[..., self.index_x]  # [B, f_in, n_so3]
        ps = self.filter()[..., self.index_psi]  # [f_in, f_out, n_so3]
        return torch.einsum("bfi,fgi->bgi", xs, ps) * self.scale  # [B, f_out, n_so3]
