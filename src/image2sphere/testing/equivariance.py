"""Assertion helpers for equivariance, used by the test suite and useful for new layers.

A layer ``phi`` from S2 (or SO(3)) signals to SO(3) signals is left-equivariant when rotating the
input by ``R`` left-translates the output: ``phi(R . x)(g) = phi(x)(R^-1 g)``. In the Fourier
domain: ``x^l -> D^l(R) x^l`` on S2 inputs, ``c^l -> D^l(R) c^l`` on SO(3) inputs and outputs.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from image2sphere.so3.rotations import random_rotations
from image2sphere.so3.wigner import left_translate_so3_coeffs, rotate_s2_coeffs

__all__ = ["assert_left_equivariant", "equivariance_error"]

_ROTATE_INPUT = {"s2": rotate_s2_coeffs, "so3": left_translate_so3_coeffs}


def equivariance_error(
    layer: Callable[[torch.Tensor], torch.Tensor],
    x: torch.Tensor,
    lmax: int,
    input_space: str,
    rotation: torch.Tensor,
) -> float:
    """``max |layer(R . x) - R . layer(x)| / max |layer(x)|`` for SO(3)-valued outputs."""
    if input_space not in _ROTATE_INPUT:
        raise ValueError(f"input_space must be 's2' or 'so3', got {input_space!r}")
    with torch.no_grad():
        out_rotated_input = layer(_ROTATE_INPUT[input_space](x, rotation, lmax))
        rotated_output = left_translate_so3_coeffs(layer(x), rotation, lmax)
    scale = rotated_output.abs().max().clamp_min(torch.finfo(x.dtype).tiny)
    return ((out_rotated_input - rotated_output).abs().max() / scale).item()


def assert_left_equivariant(
    layer: Callable[[torch.Tensor], torch.Tensor],
    x: torch.Tensor,
    lmax: int,
    input_space: str = "s2",
    n_rotations: int = 3,
    rtol: float | None = None,
    generator: torch.Generator | None = None,
) -> float:
    """Assert ``layer`` is left-equivariant on input ``x`` for random rotations; return the worst error.

    ``rtol`` defaults to 1e-9 in float64 and 1e-4 in float32 (relative to the output's max).
    """
    if rtol is None:
        rtol = 1e-9 if x.dtype == torch.float64 else 1e-4
    worst = 0.0
    for R in random_rotations(n_rotations, generator=generator, dtype=torch.float64):
        worst = max(worst, equivariance_error(layer, x, lmax, input_space, R.to(x.dtype)))
    assert worst <= rtol, f"not left-equivariant: relative error {worst:.3g} > {rtol:.3g}"
    return worst
