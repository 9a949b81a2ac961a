"""Tests for image2sphere.so3.grid against healpy / e3nn constructions and brute-force search."""

from __future__ import annotations

import math

import healpy
import numpy as np
import pytest
import torch
from e3nn import o3

from conftest import brute_force_nearest, haar_rotations, reference_grid, reference_grid_angles
from image2sphere.so3 import (
    MAX_LEVEL,
    check_level,
    gamma_major_to_pixel_major,
    geodesic_distance,
    random_rotations,
    rotvec_to_matrix,
    s2_healpix_grid,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_grid_angles,
    so3_healpix_index_to_angles,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
    so3_near_identity_grid,
)

LEVELS = [0, 1, 2, 3]


@pytest.fixture(scope="module")
def ref_grids() -> dict[int, torch.Tensor]:
    return {level: reference_grid(level) for level in LEVELS}


# ---------------------------------------------------------------------------------- the grid itself
@pytest.mark.parametrize("level", LEVELS)
def test_grid_size(level):
    G = so3_healpix_grid(level)
    assert G.shape == (72 * 8**level, 3, 3)
    assert G.dtype == torch.float32
    n_pix, n_gamma = so3_grid_size(level)
    assert (n_pix, n_gamma) == (healpy.nside2npix(2**level), 6 * 2**level)
    assert n_pix * n_gamma == 72 * 8**level


@pytest.mark.parametrize("level", LEVELS)
def test_grid_equals_healpy_construction_pixel_major(level, ref_grids):
    ref = ref_grids[level]
    G = so3_healpix_grid(level, dtype=torch.float64)
    # same order: index p * n_gamma + k
    torch.testing.assert_close(G, ref, atol=1e-12, rtol=0)
    G32 = so3_healpix_grid(level)
    torch.testing.assert_close(G32, ref.float(), atol=1e-6, rtol=0)
    # all points distinct: the smallest pairwise distance is positive
    if level <= 2:
        flat = G.reshape(-1, 9)
        tr = flat @ flat.T
        tr.fill_diagonal_(-10.0)
        assert tr.max() < 3 - 1e-6


@pytest.mark.parametrize("level", LEVELS)
def test_grid_angles_consistent(level):
    a, b, g = so3_healpix_grid_angles(level, dtype=torch.float64)
    ra, rb, rg = reference_grid_angles(level)
    np.testing.assert_allclose(a.numpy(), ra, atol=1e-15)
    np.testing.assert_allclose(b.numpy(), rb, atol=1e-15)
    np.testing.assert_allclose(g.numpy(), rg, atol=1e-15)
    torch.testing.assert_close(
        o3.angles_to_matrix(a, b, g), so3_healpix_grid(level, dtype=torch.float64), atol=1e-13, rtol=0
    )
    # gamma spacing uniform, 2 pi / (6 nside), and the fibre wraps around
    n_pix, n_gamma = so3_grid_size(level)
    gam = g.reshape(n_pix, n_gamma)
    torch.testing.assert_close(
        gam.diff(dim=1),
        torch.full((n_pix, n_gamma - 1), 2 * math.pi / n_gamma, dtype=torch.float64),
        atol=1e-13,
        rtol=0,
    )
    assert torch.all(gam[:, 0] == 0)
    # alpha, beta constant along the fibre
    assert torch.all(a.reshape(n_pix, n_gamma).diff(dim=1) == 0)
    assert torch.all(b.reshape(n_pix, n_gamma).diff(dim=1) == 0)
    # float32 angles are the float64 ones rounded
    a32, b32, g32 = so3_healpix_grid_angles(level)
    assert a32.dtype == torch.float32
    torch.testing.assert_close(g32, g.float())


@pytest.mark.parametrize("level", [0, 2])
def test_index_to_angles_and_matrix(level, ref_grids):
    N = 72 * 8**level
    idx = torch.arange(N)
    a, b, g = so3_healpix_index_to_angles(idx, level)
    ra, rb, rg = so3_healpix_grid_angles(level, dtype=torch.float64)
    torch.testing.assert_close((a, b, g), (ra, rb, rg), atol=1e-15, rtol=0)
    M = so3_healpix_index_to_matrix(idx.reshape(-1, 8), level, dtype=torch.float64)
    assert M.shape == (N // 8, 8, 3, 3)
    torch.testing.assert_close(M.reshape(-1, 3, 3), ref_grids[level], atol=1e-12, rtol=0)
    for bad in (torch.tensor([-1]), torch.tensor([N]), torch.tensor([0.5])):
        with pytest.raises(ValueError):
            so3_healpix_index_to_matrix(bad, level)


def test_equal_pixel_areas():
    # HEALPix: equal areas 4 pi / npix, so SO(3) cells have volume pi^2 / N each (Haar volume pi^2 in
    # total); this is what the density convention relies on.
    for level in LEVELS:
        nside = 2**level
        n_pix, n_gamma = so3_grid_size(level)
        assert healpy.nside2pixarea(nside) == pytest.approx(4 * math.pi / n_pix, rel=1e-14)
        assert healpy.nside2pixarea(nside) * (2 * math.pi / n_gamma) * n_pix * n_gamma / 8 == pytest.approx(math.pi**2)


def test_equivolumetric_monte_carlo():
    """Haar-random rotations fall into the level-0 Voronoi cells in roughly equal numbers."""
    n, level = 72 * 400, 0
    R = random_rotations(n, generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    grid = so3_healpix_grid(level, dtype=torch.float64)
    counts = torch.bincount(brute_force_nearest(R, grid), minlength=72).double()
    expected = n / 72
    chi2 = ((counts - expected) ** 2 / expected).sum().item()
    # chi-square with 71 dof: mean 71, std ~12. Voronoi cells are only approximately equal in
    # volume, so allow a loose bound; a grid with a doubled fibre in half the pixels would give > 2000.
    assert chi2 < 300, chi2
    assert counts.min() > 0.75 * expected and counts.max() < 1.25 * expected


# ---------------------------------------------------------------------------------- S2 grid
@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_s2_healpix_grid(level):
    nside = 2**level
    alpha, beta = s2_healpix_grid(level, dtype=torch.float64)
    assert alpha.shape == beta.shape == (12 * 4**level,)
    rb, ra = healpy.pix2ang(nside, np.arange(12 * nside * nside))
    np.testing.assert_allclose(alpha.numpy(), ra, atol=0)
    np.testing.assert_allclose(beta.numpy(), rb, atol=0)
    # the isometry: e3nn's angles_to_xyz(alpha, beta) equals healpy's pix2vec with axes permuted
    xyz = o3.angles_to_xyz(alpha, beta)
    x, y, z = healpy.pix2vec(nside, np.arange(12 * nside * nside))
    np.testing.assert_allclose(xyz.numpy(), np.stack([y, z, x], axis=1), atol=1e-12)
    for max_beta in (math.pi / 2, 1.0, 0.3):
        a, b = s2_healpix_grid(level, max_beta=max_beta, dtype=torch.float64)
        keep = rb <= max_beta
        assert len(b) == keep.sum()
        assert torch.all(b <= max_beta)
        np.testing.assert_allclose(a.numpy(), ra[keep])
    assert s2_healpix_grid(level)[0].dtype == torch.float32
    with pytest.raises(ValueError):
        s2_healpix_grid(level, max_beta=0.0)
    with pytest.raises(ValueError):
        s2_healpix_grid(level, max_beta=4.0)


# ---------------------------------------------------------------------------------- near identity
@pytest.mark.parametrize(("max_angle", "axis_level", "n_angles"), [(math.pi / 8, 1, 3), (0.3, 0, 2), (math.pi, 2, 1)])
def test_near_identity_grid(max_angle, axis_level, n_angles):
    G = so3_near_identity_grid(max_angle, axis_level=axis_level, n_angles=n_angles, dtype=torch.float64)
    assert G.shape == (1 + 12 * 4**axis_level * n_angles, 3, 3)
    eye = torch.eye(3, dtype=torch.float64)
    torch.testing.assert_close(G[0], eye, atol=0, rtol=0)
    d = geodesic_distance(eye, G)
    assert torch.all(d <= max_angle + 1e-7)
    # the angles used are max_angle * k / n_angles
    levels = torch.round(d / (max_angle / n_angles))
    torch.testing.assert_close(d, levels * (max_angle / n_angles), atol=1e-6, rtol=0)
    counts = torch.bincount(levels.long(), minlength=n_angles + 1)
    assert counts[0] == 1
    assert torch.all(counts[1:] == 12 * 4**axis_level)
    assert torch.all(torch.abs(G.transpose(-1, -2) @ G - eye).amax(dim=(-1, -2)) < 1e-12)
    assert so3_near_identity_grid().dtype == torch.float32
    assert so3_near_identity_grid().shape == (1 + 48 * 3, 3, 3)


def test_near_identity_grid_bad_input():
    for kwargs in ({"max_angle": 0.0}, {"max_angle": 4.0}, {"n_angles": 0}, {"axis_level": -1}):
        with pytest.raises(ValueError):
            so3_near_identity_grid(**kwargs)


# ---------------------------------------------------------------------------------- nearest index
@pytest.mark.parametrize("level", LEVELS)
def test_nearest_index_random_matches_brute_force(level, ref_grids):
    R = haar_rotations(1000, seed=100 + level)
    idx = so3_healpix_nearest_index(R, level)
    assert idx.dtype == torch.long and idx.shape == (1000,)
    ref = brute_force_nearest(R, ref_grids[level])
    G = ref_grids[level]
    # ties are measure-zero for random rotations; compare the trace too in case of rounding-level ties
    tr_got = (R * G[idx]).sum(dim=(-1, -2))
    tr_ref = (R * G[ref]).sum(dim=(-1, -2))
    torch.testing.assert_close(tr_got, tr_ref, atol=1e-12, rtol=0)
    assert (idx == ref).float().mean() > 0.999


@pytest.mark.parametrize("level", LEVELS)
def test_nearest_index_near_poles(level, ref_grids):
    g = torch.Generator().manual_seed(200 + level)
    n = 300
    a = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    c = torch.rand(n, generator=g, dtype=torch.float64) * 2 * math.pi
    eps = torch.tensor([1e-4, 1e-7, 0.0, 1e-2], dtype=torch.float64).repeat(n // 4 + 1)[:n]
    R = torch.cat([o3.angles_to_matrix(a, eps, c), o3.angles_to_matrix(a, math.pi - eps, c)])
    idx = so3_healpix_nearest_index(R, level)
    ref = brute_force_nearest(R, ref_grids[level])
    G = ref_grids[level]
    tr_got = (R * G[idx]).sum(dim=(-1, -2))
    tr_ref = (R * G[ref]).sum(dim=(-1, -2))
    torch.testing.assert_close(tr_got, tr_ref, atol=1e-12, rtol=0)


@pytest.mark.parametrize("level", LEVELS)
def test_nearest_index_of_grid_points_is_identity(level, ref_grids):
    G = ref_grids[level]
    N = G.shape[0]
    idx = so3_healpix_nearest_index(G, level)
    assert torch.equal(idx, torch.arange(N))
    # float32 grid points too (a subset at level 3, for time)
    step = 1 if level < 3 else 5
    idx32 = so3_healpix_nearest_index(so3_healpix_grid(level)[::step], level)
    assert torch.equal(idx32, torch.arange(N)[::step])
    # index -> matrix -> index
    sel = torch.randperm(N, generator=torch.Generator().manual_seed(level))[:200]
    n_sel = len(sel)
    assert torch.equal(so3_healpix_nearest_index(so3_healpix_index_to_matrix(sel, level), level), sel)
    # small perturbations (well inside the cell) keep the index
    w = 1e-3 * torch.randn(n_sel, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(9))
    assert torch.equal(so3_healpix_nearest_index(G[sel] @ rotvec_to_matrix(w), level), sel)


def test_nearest_index_batch_shape_and_chunking(ref_grids):
    R = haar_rotations(60, seed=300).reshape(3, 4, 5, 3, 3)
    idx = so3_healpix_nearest_index(R, 2)
    assert idx.shape == (3, 4, 5)
    flat = so3_healpix_nearest_index(R.reshape(-1, 3, 3), 2, chunk_size=7)
    assert torch.equal(idx.reshape(-1), flat)
    assert torch.equal(flat, brute_force_nearest(R.reshape(-1, 3, 3), ref_grids[2]))
    assert so3_healpix_nearest_index(R[0, 0, 0], 2).shape == ()
    assert so3_healpix_nearest_index(R.float(), 2).shape == (3, 4, 5)


def test_nearest_index_is_within_covering_radius(ref_grids):
    level = 3
    R = haar_rotations(2000, seed=301)
    G = ref_grids[level]
    d = geodesic_distance(R, G[so3_healpix_nearest_index(R, level)])
    # mean spacing ~ 7.5 deg at level 3; no rotation is farther than ~ a cell from its grid point
    assert d.max() < math.radians(7.5)
    assert d.mean() < math.radians(4.0)


def test_nearest_index_rejects_non_rotations():
    with pytest.raises(ValueError):
        so3_healpix_nearest_index(torch.eye(3) * 2, 1)
    with pytest.raises(ValueError):
        so3_healpix_nearest_index(torch.zeros(4, 3), 1)


# ---------------------------------------------------------------------------------- orders and levels
@pytest.mark.parametrize("level", [0, 1, 2])
def test_gamma_major_to_pixel_major(level, ref_grids):
    n_pix, n_gamma = so3_grid_size(level)
    nside = 2**level
    # the original code's gamma-major grid: index k * npix + p
    beta, alpha = healpy.pix2ang(nside, np.arange(n_pix))
    gamma = 2 * np.pi * np.arange(n_gamma) / n_gamma
    a = torch.as_tensor(np.tile(alpha, n_gamma))
    b = torch.as_tensor(np.tile(beta, n_gamma))
    g = torch.as_tensor(np.repeat(gamma, n_pix))
    original = o3.angles_to_matrix(a, b, g)  # [N, 3, 3], gamma-major
    idx_gm = torch.arange(n_pix * n_gamma)
    idx_pm = gamma_major_to_pixel_major(idx_gm, level)
    torch.testing.assert_close(ref_grids[level][idx_pm], original, atol=1e-13, rtol=0)
    assert torch.equal(idx_pm.sort().values, idx_gm)  # a permutation
    assert gamma_major_to_pixel_major(idx_gm.reshape(n_gamma, n_pix), level).shape == (n_gamma, n_pix)


@pytest.mark.parametrize("bad", [-1, MAX_LEVEL + 1, 11, 2.5, True, "2", None])
def test_bad_level(bad):
    with pytest.raises(ValueError):
        check_level(bad)
    with pytest.raises(ValueError):
        so3_healpix_grid(bad)
    with pytest.raises(ValueError):
        so3_grid_size(bad)
    with pytest.raises(ValueError):
        s2_healpix_grid(bad)
    with pytest.raises(ValueError):
        so3_healpix_nearest_index(torch.eye(3)[None], bad)


def test_check_level_accepts():
    assert check_level(0) == 0
    assert check_level(MAX_LEVEL) == MAX_LEVEL
    assert MAX_LEVEL == 10


@pytest.mark.parametrize("bad", [torch.tensor([-1]), torch.tensor([72 * 8]), torch.tensor([1.0])])
def test_gamma_major_to_pixel_major_rejects_bad_indices(bad):
    with pytest.raises(ValueError, match="grid indices"):
        gamma_major_to_pixel_major(bad, 1)
