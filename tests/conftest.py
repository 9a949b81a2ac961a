"""Shared fixtures and independent reference implementations for the SO(3) tests.

The references here deliberately avoid the package's own code paths: they call e3nn, healpy and
plain dense linear algebra directly.
"""

from __future__ import annotations

import math
from functools import lru_cache

import healpy
import numpy as np
import pytest
import torch
from e3nn import o3

from image2sphere.so3.wigner import default_dtype


@pytest.fixture
def single_thread():
    """Run a test with one intra-op thread (restored afterwards).

    Loops of many tiny ops (e.g. ``SO3Distribution.mode(refine=True)``) slow down ~100x when torch's
    thread pool competes with other processes for the cores; one thread makes them robust.
    """
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def haar_rotations(n: int, seed: int = 0, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """Haar-random rotations from scipy (independent of ``random_rotations``)."""
    from scipy.spatial.transform import Rotation

    return torch.as_tensor(Rotation.random(n, random_state=seed).as_matrix(), dtype=dtype)


def reference_flat_wigner(lmax: int, R: torch.Tensor) -> torch.Tensor:
    """``cat_l sqrt(2l+1) * e3nn.o3.wigner_D(l, *e3nn.o3.matrix_to_angles(R)).flatten()`` in float64."""
    with default_dtype(torch.float64):
        R = R.to(torch.float64)
        angles = o3.matrix_to_angles(R)
        blocks = [math.sqrt(2 * l + 1) * o3.wigner_D(l, *angles).reshape(*R.shape[:-2], -1) for l in range(lmax + 1)]
    return torch.cat(blocks, dim=-1)


def reference_grid_angles(level: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Pixel-major ``(alpha, beta, gamma)`` of the SO(3) HEALPix grid, straight from healpy."""
    nside = 2**level
    npix = healpy.nside2npix(nside)
    n_gamma = 6 * nside
    beta, alpha = healpy.pix2ang(nside, np.arange(npix), nest=False)
    gamma = 2 * np.pi * np.arange(n_gamma) / n_gamma
    a = np.repeat(alpha, n_gamma)
    b = np.repeat(beta, n_gamma)
    g = np.tile(gamma, npix)
    return a, b, g


def reference_grid(level: int) -> torch.Tensor:
    """Pixel-major SO(3) grid rotations in float64, built with healpy and e3nn only."""
    a, b, g = (torch.as_tensor(x, dtype=torch.float64) for x in reference_grid_angles(level))
    return o3.angles_to_matrix(a, b, g)


def brute_force_nearest(R: torch.Tensor, grid: torch.Tensor) -> torch.Tensor:
    """``argmax_i trace(R^T G_i)`` over the full grid (float64), for ``R`` of shape ``(M, 3, 3)``."""
    R = R.to(torch.float64).reshape(-1, 9)
    G = grid.to(torch.float64).reshape(-1, 9)
    return (R @ G.T).argmax(dim=1)


@lru_cache(maxsize=4)
def reference_dense_matrix(lmax: int, level: int) -> torch.Tensor:
    """Dense flat Wigner matrix ``(N, n_coeffs)`` of the pixel-major grid, float64, from e3nn.

    Uses ``D(alpha, beta, gamma) = D(alpha, beta, 0) @ D(0, 0, gamma)`` (a group homomorphism, tested
    in test_so3_wigner) so that level 3 stays fast.
    """
    a, b, _ = reference_grid_angles(level)
    n_gamma = 6 * 2**level
    alpha = torch.as_tensor(a[::n_gamma], dtype=torch.float64)  # [P]
    beta = torch.as_tensor(b[::n_gamma], dtype=torch.float64)  # [P]
    gamma = 2 * math.pi * torch.arange(n_gamma, dtype=torch.float64) / n_gamma  # [G]
    cols = []
    with default_dtype(torch.float64):
        for l in range(lmax + 1):
            A = o3.wigner_D(l, alpha, beta, torch.zeros_like(alpha))  # [P, d, d]
            C = o3.wigner_D(l, torch.zeros_like(gamma), torch.zeros_like(gamma), gamma)  # [G, d, d]
            D = torch.einsum("pij,gjk->pgik", A, C)  # [P, G, d, d]
            cols.append(math.sqrt(2 * l + 1) * D.reshape(len(alpha) * n_gamma, -1))
    return torch.cat(cols, dim=1)


def reference_dense_grid_logits(coeffs: torch.Tensor, lmax: int, level: int) -> torch.Tensor:
    """``coeffs @ D.T`` with the dense reference matrix, ``(B, N)`` in float64 (differentiable)."""
    return coeffs.to(torch.float64) @ reference_dense_matrix(lmax, level).T
