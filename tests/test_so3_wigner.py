"""Tests for image2sphere.so3.wigner against e3nn, representation theory and analytic characters."""

from __future__ import annotations

import math

import pytest
import torch
from e3nn import o3
from scipy.spatial.transform import Rotation

from conftest import haar_rotations, reference_flat_wigner
from image2sphere.so3 import (
    angles_to_matrix,
    check_lmax,
    flat_wigner,
    flat_wigner_from_angles,
    flat_wigner_on_euler_grid,
    left_translate_so3_coeffs,
    lmax_from_n_so3_coeffs,
    matrix_to_angles,
    n_s2_coeffs,
    n_so3_coeffs,
    rotate_s2_coeffs,
    so3_layout,
    wigner_D,
)
from image2sphere.so3.wigner import default_dtype


def blocks(flat: torch.Tensor, lmax: int) -> list[torch.Tensor]:
    """Split a flat Wigner vector ``(..., n)`` into ``D^l`` matrices (the sqrt(2l+1) factor removed)."""
    out, offset = [], 0
    for l in range(lmax + 1):
        d = 2 * l + 1
        out.append(flat[..., offset : offset + d * d].reshape(*flat.shape[:-1], d, d) / math.sqrt(d))
        offset += d * d
    assert offset == flat.shape[-1]
    return out


def character(l: int, theta: torch.Tensor) -> torch.Tensor:
    """``trace D^l`` of a rotation by ``theta``: ``sum_{m=-l..l} cos(m theta)``."""
    m = torch.arange(-l, l + 1, dtype=theta.dtype)
    return torch.cos(theta[..., None] * m).sum(-1)


# ---------------------------------------------------------------------------------- sizes
def test_n_so3_coeffs_formula():
    for lmax in range(11):
        assert n_so3_coeffs(lmax) == sum((2 * l + 1) ** 2 for l in range(lmax + 1))
        assert n_s2_coeffs(lmax) == sum(2 * l + 1 for l in range(lmax + 1))
        assert lmax_from_n_so3_coeffs(n_so3_coeffs(lmax)) == lmax
    assert n_so3_coeffs(6) == 455
    assert n_so3_coeffs(4) == 165
    assert n_s2_coeffs(6) == 49


@pytest.mark.parametrize("n", [456, 454, 2, 0, 11, 166])
def test_lmax_from_n_so3_coeffs_rejects(n):
    with pytest.raises(ValueError):
        lmax_from_n_so3_coeffs(n)


@pytest.mark.parametrize("bad", [-1, 2.5, True, None, "3"])
def test_bad_lmax(bad):
    R = torch.eye(3)[None]
    with pytest.raises(ValueError):
        check_lmax(bad)
    with pytest.raises(ValueError):
        n_so3_coeffs(bad)
    with pytest.raises(ValueError):
        flat_wigner(bad, R)
    with pytest.raises(ValueError):
        flat_wigner_from_angles(bad, torch.zeros(1), torch.zeros(1), torch.zeros(1))


def test_check_lmax_accepts():
    assert check_lmax(0) == 0
    assert check_lmax(10) == 10


@pytest.mark.parametrize("lmax", [0, 1, 3, 6])
def test_so3_layout(lmax):
    l, m, n = so3_layout(lmax)
    N = n_so3_coeffs(lmax)
    assert l.shape == m.shape == n.shape == (N,)
    assert l.dtype == m.dtype == n.dtype == torch.long
    expected = [(ll, mm, nn) for ll in range(lmax + 1) for mm in range(2 * ll + 1) for nn in range(2 * ll + 1)]
    assert list(zip(l.tolist(), m.tolist(), n.tolist(), strict=True)) == expected
    # consistent with flat_wigner: entry i is sqrt(2l+1) D^l[m, n]
    R = haar_rotations(4, seed=lmax)
    flat = flat_wigner(lmax, R)
    angles = matrix_to_angles(R)
    for ll in range(lmax + 1):
        D = wigner_D(ll, *angles)
        sel = l == ll
        torch.testing.assert_close(flat[:, sel], math.sqrt(2 * ll + 1) * D[:, m[sel], n[sel]], atol=1e-13, rtol=0)


# ---------------------------------------------------------------------------------- values
@pytest.mark.parametrize("lmax", [0, 1, 2, 6])
def test_flat_wigner_matches_e3nn(lmax):
    R = haar_rotations(64, seed=10 + lmax)
    got = flat_wigner(lmax, R)
    assert got.shape == (64, n_so3_coeffs(lmax))
    assert got.dtype == torch.float64
    torch.testing.assert_close(got, reference_flat_wigner(lmax, R), atol=1e-11, rtol=0)


def test_flat_wigner_length_455_and_batch_shapes():
    R = haar_rotations(24, seed=20).reshape(2, 3, 4, 3, 3)
    got = flat_wigner(6, R)
    assert got.shape == (2, 3, 4, 455)
    torch.testing.assert_close(got.reshape(-1, 455), reference_flat_wigner(6, R.reshape(-1, 3, 3)), atol=1e-11, rtol=0)
    single = flat_wigner(6, R[0, 0, 0])
    assert single.shape == (455,)
    torch.testing.assert_close(single, got[0, 0, 0], atol=1e-13, rtol=0)


def test_flat_wigner_float32():
    R = haar_rotations(32, seed=21)
    got = flat_wigner(6, R.float())
    assert got.dtype == torch.float32
    ref = reference_flat_wigner(6, R)
    assert (got.double() - ref).abs().max() < 1e-4 * ref.abs().max()


def test_float64_precision_needs_default_dtype():
    """In float64 the result is float64-accurate even when the default dtype is float32."""
    assert torch.get_default_dtype() == torch.float32
    R = haar_rotations(16, seed=22)
    D = wigner_D(6, *matrix_to_angles(R))
    eye = torch.eye(13, dtype=torch.float64).expand_as(D)
    torch.testing.assert_close(D @ D.transpose(-1, -2), eye, atol=1e-12, rtol=0)
    # the context manager restores the default dtype, also on error
    with default_dtype(torch.float64):
        assert torch.get_default_dtype() == torch.float64
    assert torch.get_default_dtype() == torch.float32
    with pytest.raises(RuntimeError), default_dtype(torch.float64):
        raise RuntimeError("boom")
    assert torch.get_default_dtype() == torch.float32


def test_flat_wigner_from_angles_consistent():
    g = torch.Generator().manual_seed(23)
    a = torch.rand(30, generator=g, dtype=torch.float64) * 2 * math.pi
    b = torch.rand(30, generator=g, dtype=torch.float64) * math.pi
    c = torch.rand(30, generator=g, dtype=torch.float64) * 2 * math.pi
    via_angles = flat_wigner_from_angles(4, a, b, c)
    via_matrix = flat_wigner(4, angles_to_matrix(a, b, c))
    torch.testing.assert_close(via_angles, via_matrix, atol=1e-11, rtol=0)
    # direct e3nn on the same angles (no matrix round trip)
    with default_dtype(torch.float64):
        ref = torch.cat([math.sqrt(2 * l + 1) * o3.wigner_D(l, a, b, c).flatten(-2) for l in range(5)], -1)
    torch.testing.assert_close(via_angles, ref, atol=1e-12, rtol=0)
    # broadcasting of the angles
    out = flat_wigner_from_angles(2, a[:, None], b[None, :5], torch.zeros(()))
    assert out.shape == (30, 5, 35)


def test_flat_wigner_on_a_product_grid_is_e3nns_at_every_point():
    """Quick. The product grid's matrices, composed from each angle's own, against e3nn's ``wigner_D`` at
    every point (irregular angles of three different counts) in float64, and rounded once in float32."""
    g = torch.Generator().manual_seed(0)
    alpha, beta, gamma = (torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi for n in (5, 3, 4))
    grid = flat_wigner_on_euler_grid(5, alpha, beta, gamma)  # [5, 3, 4, n]
    assert grid.shape == (5, 3, 4, n_so3_coeffs(5)) and grid.dtype == torch.float64
    A, B, C = torch.meshgrid(alpha, beta, gamma, indexing="ij")
    with default_dtype(torch.float64):
        expected = torch.cat([math.sqrt(2 * l + 1) * o3.wigner_D(l, A, B, C).flatten(-2) for l in range(6)], -1)
    torch.testing.assert_close(grid, expected, rtol=0, atol=1e-12)
    single = flat_wigner_on_euler_grid(5, alpha.float(), beta.float(), gamma.float())
    assert single.dtype == torch.float32
    torch.testing.assert_close(single, expected.float(), rtol=0, atol=1e-5)  # float32 angles, then rounded once
    with pytest.raises(ValueError, match=r"beta must have shape \(n,\), got \(3, 1\)"):
        flat_wigner_on_euler_grid(2, alpha, beta[:, None], gamma)


def test_identity_and_l1():
    eye = torch.eye(3, dtype=torch.float64)
    for l, D in enumerate(blocks(flat_wigner(6, eye), 6)):
        torch.testing.assert_close(D, torch.eye(2 * l + 1, dtype=torch.float64), atol=1e-12, rtol=0)
    # e3nn's real l=1 representation is the rotation matrix itself (basis x, y, z)
    R = haar_rotations(10, seed=24)
    torch.testing.assert_close(blocks(flat_wigner(1, R), 1)[1], R, atol=1e-12, rtol=0)
    # l = 0 entry is always 1
    assert torch.all(flat_wigner(3, R)[:, 0] == 1)


# ---------------------------------------------------------------------------------- representation theory
def test_homomorphism_and_orthogonality():
    lmax = 6
    R1 = haar_rotations(20, seed=25)
    R2 = haar_rotations(20, seed=26)
    B1, B2, B12 = (blocks(flat_wigner(lmax, R), lmax) for R in (R1, R2, R1 @ R2))
    Binv = blocks(flat_wigner(lmax, R1.transpose(-1, -2)), lmax)
    for l in range(lmax + 1):
        torch.testing.assert_close(B12[l], B1[l] @ B2[l], atol=1e-11, rtol=0)
        eye = torch.eye(2 * l + 1, dtype=torch.float64).expand_as(B1[l])
        torch.testing.assert_close(B1[l] @ B1[l].transpose(-1, -2), eye, atol=1e-12, rtol=0)
        torch.testing.assert_close(Binv[l], B1[l].transpose(-1, -2), atol=1e-11, rtol=0)


def test_character_formula():
    """trace D^l(R) depends only on the rotation angle: sum_m cos(m theta)."""
    R = haar_rotations(50, seed=27)
    theta = torch.as_tensor(Rotation.from_matrix(R.numpy()).magnitude(), dtype=torch.float64)
    for l, D in enumerate(blocks(flat_wigner(6, R), 6)):
        torch.testing.assert_close(D.diagonal(dim1=-2, dim2=-1).sum(-1), character(l, theta), atol=1e-11, rtol=0)


def test_so3_signal_of_a_delta_is_a_character_sum():
    """f(R) = flat_wigner(R) @ flat_wigner(R0) = sum_l (2l+1) chi_l(angle(R0^T R)), maximal at R0."""
    lmax = 6
    R0 = haar_rotations(1, seed=28)[0]
    c = flat_wigner(lmax, R0)
    R = haar_rotations(200, seed=29)
    f = flat_wigner(lmax, R) @ c
    rel = R0.T @ R
    theta = torch.arccos(((rel.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    expected = sum((2 * l + 1) * character(l, theta) for l in range(lmax + 1))
    torch.testing.assert_close(f, expected, atol=1e-9, rtol=0)
    # equivalently sum_l (2l+1) trace D^l(R0^T R)
    via_trace = sum(
        (2 * l + 1) * D.diagonal(dim1=-2, dim2=-1).sum(-1) for l, D in enumerate(blocks(flat_wigner(lmax, rel), lmax))
    )
    torch.testing.assert_close(f, via_trace, atol=1e-9, rtol=0)
    # maximum n_so3_coeffs at R0, strictly smaller elsewhere
    f0 = flat_wigner(lmax, R0) @ c
    assert f0.item() == pytest.approx(n_so3_coeffs(lmax), abs=1e-9)
    assert torch.all(f < f0 - 1e-6)
    # left-invariance: the signal of g R0 at g R equals that of R0 at R
    g = haar_rotations(1, seed=30)[0]
    f_moved = flat_wigner(lmax, g @ R) @ flat_wigner(lmax, g @ R0)
    torch.testing.assert_close(f_moved, f, atol=1e-9, rtol=0)


def test_flat_wigner_rejects_non_rotations():
    with pytest.raises(ValueError):
        flat_wigner(2, 2 * torch.eye(3))
    with pytest.raises(ValueError):
        flat_wigner(2, torch.eye(4))
    with pytest.raises(ValueError):
        flat_wigner(2, torch.diag(torch.tensor([1.0, 1.0, -1.0])))


# ---------------------------------------------------------------------------------- rotating coefficients
def test_left_translate_so3_coeffs():
    """f'(g) = f(R^-1 g) for the left-translated coefficients, evaluated with e3nn Wigner matrices."""
    lmax = 4
    c = torch.randn(2, n_so3_coeffs(lmax), dtype=torch.float64, generator=torch.Generator().manual_seed(40))
    R = haar_rotations(1, seed=41)[0]
    g = haar_rotations(30, seed=42)
    moved = left_translate_so3_coeffs(c, R, lmax)
    assert moved.shape == c.shape
    got = reference_flat_wigner(lmax, g) @ moved.T
    expected = reference_flat_wigner(lmax, R.T @ g) @ c.T
    torch.testing.assert_close(got, expected, atol=1e-10, rtol=0)
    # a group action: translating by R1 then R2 equals translating by R2 R1; identity does nothing
    R2 = haar_rotations(1, seed=43)[0]
    torch.testing.assert_close(
        left_translate_so3_coeffs(moved, R2, lmax), left_translate_so3_coeffs(c, R2 @ R, lmax), atol=1e-11, rtol=0
    )
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(left_translate_so3_coeffs(c, eye, lmax), c, atol=1e-12, rtol=0)
    with pytest.raises(ValueError):
        left_translate_so3_coeffs(c[:, :-1], R, lmax)
    with pytest.raises(ValueError):
        left_translate_so3_coeffs(c, 2 * eye, lmax)


def test_rotate_s2_coeffs():
    """x'(u) = x(R^-1 u) with e3nn real spherical harmonics (component normalisation)."""
    lmax = 5
    x = torch.randn(3, n_s2_coeffs(lmax), dtype=torch.float64, generator=torch.Generator().manual_seed(44))
    R = haar_rotations(1, seed=45)[0]
    u = torch.nn.functional.normalize(
        torch.randn(40, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(46)), dim=-1
    )

    def sh(v):
        return o3.spherical_harmonics(list(range(lmax + 1)), v, normalize=True, normalization="component")

    rotated = rotate_s2_coeffs(x, R, lmax)
    assert rotated.shape == x.shape
    torch.testing.assert_close(sh(u) @ rotated.T, sh(u @ R) @ x.T, atol=1e-10, rtol=0)  # u @ R = R^-1 u
    with pytest.raises(ValueError):
        rotate_s2_coeffs(x[:, :-1], R, lmax)


@pytest.mark.parametrize("bad", [True, 455.0, 0, -3, "455"])
def test_lmax_from_n_so3_coeffs_rejects_non_integers(bad):
    with pytest.raises(ValueError, match=r"number of SO\(3\) coefficients must be an integer >= 1"):
        lmax_from_n_so3_coeffs(bad)


@pytest.mark.parametrize("lmax", [0, 1, 6])
def test_so3_blocks_tile_the_flat_layout(lmax):
    from image2sphere.so3 import so3_blocks

    l_of, _, _ = so3_layout(lmax)
    blocks = so3_blocks(lmax)
    assert [l for l, _ in blocks] == list(range(lmax + 1))
    assert blocks[0][1].start == 0 and blocks[-1][1].stop == n_so3_coeffs(lmax)
    for (_, block), (_, nxt) in zip(blocks[:-1], blocks[1:], strict=True):
        assert block.stop == nxt.start
    for l, block in blocks:
        assert (l_of[block] == l).all() and block.stop - block.start == (2 * l + 1) ** 2
