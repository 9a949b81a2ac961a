"""SO(3) group convolution with a locally supported filter, in the Fourier domain.

Conventions
-----------
Signals are in the flat Wigner layout: ``f(R) = sum_l sqrt(2l+1) sum_{mn} F^l[m,n] D^l(R)[m,n]``.
The filter is a weighted sum of point masses at rotations ``g_k`` within ``max_angle`` of the
identity; for one input and output channel the convolution is

    out(R) = sum_k w_k f(R g_k) * scale,

which in the Fourier domain is ``out^l = F^l @ Psi^l^T / sqrt(2l+1)`` with
``Psi = sum_k w_k flat_wigner(g_k)``. Rotating the input (``f -> f(Q^-1 .)``) left-translates
the output the same way: the layer is SO(3)-equivariant.

Initialisation (``init``): ``"unit"`` (default) draws ``w ~ N(0, 1)`` with
``scale = 1 / sqrt(f_in * K)``, which keeps the mean square of its input. ``"fan_in"`` draws
``w ~ N(0, 2 / (f_in * K))`` and uses ``scale = 1``, like ``nn.Linear`` after a ReLU (Kaiming's
gain 2: the layer follows the SO(3) ReLU, which halves a zero-mean signal's mean square).
``"kaiming_uniform"`` is ``"unit"`` here: it names the original research code's combination, whose
S2 convolution draws its filter with ``kaiming_uniform_`` (:mod:`image2sphere.nn.s2_conv`) while its
SO(3) convolutions draw ``N(0, 1)`` parameters scaled by ``1 / sqrt(fan_in)`` in the forward pass.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from image2sphere.checks import ConfigError
from image2sphere.so3.grid import so3_near_identity_grid
from image2sphere.so3.wigner import check_lmax, flat_wigner, n_so3_coeffs, so3_blocks

__all__ = ["SO3Conv"]

INITS = ("fan_in", "kaiming_uniform", "unit")


class SO3Conv(nn.Module):
    """SO(3) convolution ``[B, f_in, n_so3_coeffs] -> [B, f_out, n_so3_coeffs]``.

    Args:
        max_angle: support of the filter around the identity (radians; 22.5 deg in the paper).
        axis_level, n_angles: the kernel grid, see :func:`image2sphere.so3.so3_near_identity_grid`.
        kernel: optional explicit kernel rotations ``(K, 3, 3)`` instead of the near-identity grid.
        init: ``"unit"``, ``"fan_in"`` or ``"kaiming_uniform"`` (the same as ``"unit"`` here), see the
            module docstring.
    """

    def __init__(
        self,
        in_channels: int,
        out_channels: int,
        lmax: int = 6,
        max_angle: float = math.pi / 8,
        axis_level: int = 1,
        n_angles: int = 3,
        kernel: torch.Tensor | None = None,
        init: str = "unit",
    ):
        super().__init__()
        self.lmax = check_lmax(lmax)
        self.in_channels, self.out_channels = in_channels, out_channels
        if kernel is None:
            kernel = so3_near_identity_grid(max_angle, axis_level, n_angles, dtype=torch.float64)
        if init not in INITS:
            raise ConfigError(f"init must be one of {INITS}, got {init!r}")
        self.init = init
        D = flat_wigner(lmax, kernel.to(torch.float64))  # [K, n_so3]
        self.register_buffer("kernel_D", D.float(), persistent=False)
        fan_in = in_channels * len(kernel)
        std = math.sqrt(2 / fan_in) if init == "fan_in" else 1.0
        self.scale = 1.0 if init == "fan_in" else 1 / math.sqrt(fan_in)
        self.weight = nn.Parameter(torch.randn(in_channels, out_channels, len(kernel)) * std)

    def filter(self) -> torch.Tensor:
        """The filter's SO(3) coefficients ``[f_in, f_out, n_so3_coeffs]`` (flat Wigner layout)."""
        f, g, k = self.weight.shape
        # one matrix product on the weight's contiguous rows, so that the weight's gradient has the weight's own
        # strides also when out_channels is 1 (an einsum gives a size-1 dimension another stride, and DDP's
        # reducer then copies the gradient and warns "Grad strides do not match bucket view strides")
        return (self.weight.reshape(f * g, k) @ self.kernel_D).unflatten(0, (f, g))  # [f_in, f_out, n_so3_coeffs]

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        n = n_so3_coeffs(self.lmax)
        if x.ndim != 3 or x.shape[1:] != (self.in_channels, n):
            raise ConfigError(f"SO(3) input must have shape (batch, {self.in_channels}, {n}), got {tuple(x.shape)}")
        psi = self.filter()
        out = []
        for l, block in so3_blocks(self.lmax):
            d = 2 * l + 1
            F = x[..., block].unflatten(-1, (d, d))  # [B, f_in, d, d]
            P = psi[..., block].unflatten(-1, (d, d))  # [f_in, f_out, d, d]
            block = torch.einsum("bfmk,fgnk->bgmn", F, P) * (self.scale / math.sqrt(d))  # [B, f_out, d, d]
            out.append(block.flatten(-2))
        return torch.cat(out, dim=-1)
