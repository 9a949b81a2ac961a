"""Tests for image2sphere.distributions.fourier.SO3Distribution."""

from __future__ import annotations

import math

import pytest
import torch

from conftest import brute_force_nearest, haar_rotations, reference_dense_grid_logits, reference_flat_wigner
from image2sphere.distributions import LOG_UNIFORM_DENSITY, SO3Distribution
from image2sphere.so3 import (
    flat_wigner,
    geodesic_distance,
    n_so3_coeffs,
    so3_healpix_grid,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)

LMAX = 6
FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))


def peaked(R0: torch.Tensor, scale: float = 1.0) -> SO3Distribution:
    """Distribution whose signal is ``scale * sum_l (2l+1) chi_l(angle(R0^T R))``: a peak at ``R0``."""
    return SO3Distribution(scale * flat_wigner(LMAX, R0), LMAX)


# ---------------------------------------------------------------------------------- uniform
@pytest.mark.parametrize("level", [0, 1, 2, 3])
def test_uniform_distribution(level):
    B = 2
    dist = SO3Distribution(torch.zeros(B, 455, dtype=torch.float64), LMAX)
    assert dist.batch_size == B
    assert LOG_UNIFORM_DENSITY == pytest.approx(-math.log(math.pi**2))
    assert LOG_UNIFORM_DENSITY == pytest.approx(-2.2894, abs=1e-4)
    R = haar_rotations(10, seed=level)
    ld = dist.log_density(R, level)
    assert ld.shape == (B, 10)
    torch.testing.assert_close(ld, torch.full((B, 10), -math.log(math.pi**2), dtype=torch.float64), atol=1e-10, rtol=0)
    N = 72 * 8**level
    logits = dist.grid_logits(level)
    assert logits.shape == (B, N)
    lp = dist.log_prob_grid(level)
    torch.testing.assert_close(lp.exp().sum(dim=1), torch.ones(B, dtype=torch.float64), atol=1e-10, rtol=0)
    torch.testing.assert_close(lp, torch.full((B, N), -math.log(N), dtype=torch.float64), atol=1e-10, rtol=0)
    torch.testing.assert_close(
        dist.log_normalizer(level), torch.full((B,), math.log(N), dtype=torch.float64), atol=1e-10, rtol=0
    )


def test_uniform_float32():
    dist = SO3Distribution(torch.zeros(3, 455), LMAX)
    ld = dist.log_density(haar_rotations(5, seed=1, dtype=torch.float32), 2)
    assert ld.dtype == torch.float32 and ld.shape == (3, 5)
    torch.testing.assert_close(ld, torch.full((3, 5), LOG_UNIFORM_DENSITY), atol=1e-4, rtol=0)


# ---------------------------------------------------------------------------------- values
def test_logits_at_arbitrary_rotations():
    B, K = 3, 7
    coeffs = torch.randn(B, 455, dtype=torch.float64, generator=torch.Generator().manual_seed(0))
    dist = SO3Distribution(coeffs, LMAX)
    R_shared = haar_rotations(K, seed=1)
    got = dist.logits(R_shared)
    assert got.shape == (B, K)
    torch.testing.assert_close(got, coeffs @ reference_flat_wigner(LMAX, R_shared).T, atol=1e-10, rtol=0)
    R_per = haar_rotations(B * K, seed=2).reshape(B, K, 3, 3)
    got = dist.logits(R_per)
    expected = torch.einsum("bkn,bn->bk", reference_flat_wigner(LMAX, R_per), coeffs)
    torch.testing.assert_close(got, expected, atol=1e-10, rtol=0)
    # float32 coefficients, float64 queries: the result follows the coefficients
    d32 = SO3Distribution(coeffs.float(), LMAX)
    out = d32.logits(R_shared)
    assert out.dtype == torch.float32
    torch.testing.assert_close(out.double(), dist.logits(R_shared), atol=1e-4 * 30, rtol=1e-4)


def test_grid_values_match_dense_reference():
    coeffs = torch.randn(2, 455, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    dist = SO3Distribution(coeffs, LMAX)
    level = 2
    ref = reference_dense_grid_logits(coeffs, LMAX, level)
    torch.testing.assert_close(dist.grid_logits(level), ref, atol=1e-9, rtol=0)
    torch.testing.assert_close(dist.log_prob_grid(level), torch.log_softmax(ref, 1), atol=1e-9, rtol=0)
    torch.testing.assert_close(dist.log_normalizer(level), torch.logsumexp(ref, 1), atol=1e-9, rtol=0)
    idx = torch.tensor([[0, 5, 1535], [9, 9, 100]])
    torch.testing.assert_close(
        dist.log_prob_at_index(idx, level), torch.log_softmax(ref, 1).gather(1, idx), atol=1e-9, rtol=0
    )
    torch.testing.assert_close(
        dist.log_prob_at_index(idx[0], level), torch.log_softmax(ref, 1)[:, idx[0]], atol=1e-9, rtol=0
    )


def test_log_density_reads_the_nearest_grid_point():
    B, level = 3, 2
    R0 = haar_rotations(B, seed=4)
    dist = peaked(R0, scale=0.05)
    N = 72 * 8**level
    log_p = torch.log_softmax(reference_dense_grid_logits(dist.coeffs, LMAX, level), dim=1)  # [B, N]
    grid = so3_healpix_grid(level, dtype=torch.float64)
    # at R0 itself: (B, 1, 3, 3) queries
    ld0 = dist.log_density(R0[:, None], level)
    nearest = brute_force_nearest(R0, grid)  # [B]
    expected = log_p.gather(1, nearest[:, None]) + math.log(N / math.pi**2)
    torch.testing.assert_close(ld0, expected, atol=1e-9, rtol=0)
    # shared random queries (K, 3, 3)
    Q = haar_rotations(20, seed=5)
    nq = brute_force_nearest(Q, grid)
    torch.testing.assert_close(dist.log_density(Q, level), log_p[:, nq] + math.log(N / math.pi**2), atol=1e-9, rtol=0)
    # the peak is denser than the antipode (rotation by pi away) and than uniform
    far = dist.log_density((R0 @ FLIP)[:, None], level)
    assert torch.all(ld0 > far + 1.0)
    assert torch.all(ld0 > LOG_UNIFORM_DENSITY)
    assert torch.all(far < LOG_UNIFORM_DENSITY)
    # normalised: the mean of exp(log density) over the grid cells is 1 / pi^2 per unit volume
    cell = math.pi**2 / N
    ld_grid = dist.log_density(grid, level)
    torch.testing.assert_close((ld_grid.exp() * cell).sum(1), torch.ones(B, dtype=torch.float64), atol=1e-9, rtol=0)


def test_log_prob_gradients_match_dense():
    """The training loss (log p at the label's grid index) has the gradient of the dense log-softmax."""
    level = 1
    coeffs = torch.randn(2, 455, dtype=torch.float64, generator=torch.Generator().manual_seed(6))
    R = haar_rotations(2, seed=7)
    a = coeffs.clone().requires_grad_(True)
    b = coeffs.clone().requires_grad_(True)
    SO3Distribution(a, LMAX).log_density(R[:, None], level).sum().backward()
    idx = brute_force_nearest(R, so3_healpix_grid(level, dtype=torch.float64))
    torch.log_softmax(reference_dense_grid_logits(b, LMAX, level), 1).gather(1, idx[:, None]).sum().backward()
    torch.testing.assert_close(a.grad, b.grad, atol=1e-10, rtol=0)
    assert a.grad.abs().max() > 1e-3


# ---------------------------------------------------------------------------------- mode
@pytest.mark.parametrize("level", [1, 2, 3])
def test_mode_is_nearest_grid_point(level):
    R0 = haar_rotations(4, seed=10 + level)
    dist = peaked(R0)
    mode = dist.mode(level)
    assert mode.shape == (4, 3, 3) and mode.dtype == torch.float64
    nearest = so3_healpix_nearest_index(R0, level)
    torch.testing.assert_close(
        mode, so3_healpix_index_to_matrix(nearest, level, dtype=torch.float64), atol=1e-12, rtol=0
    )
    # within the grid's covering radius (~ 60 / 2**level degrees)
    err = torch.rad2deg(geodesic_distance(mode, R0))
    assert torch.all(err < 55.0 / 2**level), err


@pytest.mark.parametrize("level", [2, 3])
@pytest.mark.usefixtures("single_thread")
def test_mode_refined(level):
    R0 = haar_rotations(4, seed=20 + level)
    dist = peaked(R0)
    coarse = torch.rad2deg(geodesic_distance(dist.mode(level), R0))
    refined = dist.mode(level, refine=True)
    fine = torch.rad2deg(geodesic_distance(refined, R0))
    assert torch.all(fine < 0.5), fine
    assert fine.mean() < coarse.mean() / 4
    eye = torch.eye(3, dtype=torch.float64).expand_as(refined)
    torch.testing.assert_close(refined.transpose(-1, -2) @ refined, eye, atol=1e-10, rtol=0)
    # float32 coefficients work too
    d32 = SO3Distribution(dist.coeffs.float(), LMAX)
    fine32 = torch.rad2deg(geodesic_distance(d32.mode(level, refine=True).double(), R0))
    assert torch.all(fine32 < 1.0), fine32


# ---------------------------------------------------------------------------------- sampling
def test_sample_matches_grid_softmax():
    level, n = 1, 40000
    R0 = haar_rotations(2, seed=30)
    dist = peaked(R0, scale=0.01)  # a broad peak: ~200-300 of the 576 grid points carry the mass
    p = torch.softmax(reference_dense_grid_logits(dist.coeffs, LMAX, level), dim=1)  # [2, 576]
    rot, idx = dist.sample(n, level, generator=torch.Generator().manual_seed(0), return_index=True)
    assert rot.shape == (2, n, 3, 3) and idx.shape == (2, n)
    assert idx.dtype == torch.long and idx.min() >= 0 and idx.max() < 576
    counts = torch.stack([torch.bincount(i, minlength=576) for i in idx]).double()
    freq = counts / n
    # total variation: under exact sampling E[TV] ~ 0.5 * sum sqrt(2 p (1 - p) / (pi n)) (~0.047 here),
    # with a spread of a few percent of that
    tv = 0.5 * (freq - p).abs().sum(dim=1)
    expected_tv = 0.5 * torch.sqrt(2 * p * (1 - p) / (math.pi * n)).sum(dim=1)
    assert torch.all(tv < 1.25 * expected_tv), (tv, expected_tv)
    # on the 48 pixels (gamma marginal) the TV is small in absolute terms
    pix_tv = 0.5 * (freq.reshape(2, 48, 12).sum(2) - p.reshape(2, 48, 12).sum(2)).abs().sum(1)
    assert torch.all(pix_tv < 0.03), pix_tv
    # chi-square over the bins with expected count >= 5
    for b in range(2):
        keep = n * p[b] >= 5
        k = int(keep.sum())
        chi2 = ((counts[b, keep] - n * p[b, keep]) ** 2 / (n * p[b, keep])).sum().item()
        assert k > 100
        assert chi2 < k + 5 * math.sqrt(2 * k), (chi2, k)
    # E[p(X)] = sum p^2
    torch.testing.assert_close(p.gather(1, idx).mean(1), (p**2).sum(1), atol=0, rtol=0.05)
    # indices consistent with the rotations
    grid = so3_healpix_grid(level, dtype=torch.float64)
    torch.testing.assert_close(rot, grid[idx], atol=1e-12, rtol=0)


def test_sample_reproducible_and_shapes():
    dist = peaked(haar_rotations(3, seed=31), scale=0.05)
    a = dist.sample(50, 2, generator=torch.Generator().manual_seed(5))
    b = dist.sample(50, 2, generator=torch.Generator().manual_seed(5))
    c = dist.sample(50, 2, generator=torch.Generator().manual_seed(6))
    assert a.shape == (3, 50, 3, 3)
    assert torch.equal(a, b)
    assert not torch.equal(a, c)
    # same draws with return_index; the rotations are grid points that map back to their indices
    r, idx = dist.sample(50, 2, generator=torch.Generator().manual_seed(5), return_index=True)
    assert torch.equal(r, a)
    assert torch.equal(so3_healpix_nearest_index(a, 2), idx)


def test_sample_peaked_lands_on_mode():
    R0 = haar_rotations(2, seed=32)
    dist = peaked(R0, scale=3.0)  # very sharp: essentially all mass on the argmax
    _, idx = dist.sample(200, 2, generator=torch.Generator().manual_seed(1), return_index=True)
    mode_idx = so3_healpix_nearest_index(dist.mode(2), 2)
    assert (idx == mode_idx[:, None]).double().mean() > 0.95


# ---------------------------------------------------------------------------------- bad input
def test_bad_input():
    with pytest.raises(ValueError):
        SO3Distribution(torch.zeros(2, 454), LMAX)
    with pytest.raises(ValueError):
        SO3Distribution(torch.zeros(455), LMAX)
    with pytest.raises(ValueError):
        SO3Distribution(torch.zeros(2, 455, dtype=torch.long), LMAX)
    with pytest.raises(ValueError):
        SO3Distribution(torch.zeros(2, 1), -1)
    with pytest.raises(ValueError):
        SO3Distribution(torch.zeros(2, 455), 6.0)
    with pytest.raises(ValueError):
        SO3Distribution([[0.0] * 455], LMAX)
    dist = SO3Distribution(torch.zeros(2, 455), LMAX)
    for query in (
        2 * torch.eye(3)[None],  # not a rotation
        torch.diag(torch.tensor([1.0, 1.0, -1.0]))[None],  # reflection
        torch.eye(3)[None, None].expand(3, 4, 3, 3),  # B' = 3 != 2
        torch.eye(3),  # missing K
        torch.eye(3).expand(2, 2, 2, 3, 3),  # too many dims
    ):
        with pytest.raises(ValueError):
            dist.logits(query)
        with pytest.raises(ValueError):
            dist.log_density(query, 1)
    for n in (0, -3, 2.0, True):
        with pytest.raises(ValueError):
            dist.sample(n, 2)
    for level in (-1, 11, 2.5):
        with pytest.raises(ValueError):
            dist.grid_logits(level)
        with pytest.raises(ValueError):
            dist.mode(level)


def test_refinement_works_under_inference_mode():
    """Lightning's test loop runs under torch.inference_mode; refinement must still use autograd."""
    target = haar_rotations(1, seed=8)
    dist = SO3Distribution(0.05 * flat_wigner(4, target), 4)
    plain = dist.mode(2, refine=True, steps=30)
    with torch.inference_mode():
        inside = SO3Distribution(dist.coeffs.clone(), 4).mode(2, refine=True, steps=30)
    torch.testing.assert_close(inside, plain)
    assert geodesic_distance(plain, target).item() < geodesic_distance(dist.mode(2), target).item()


def test_set_loss_averages_the_dense_cross_entropy_over_the_equivalent_rotations():
    """I2S's loss for dataset.label=all, against the dense grid softmax: ``logsumexp - mean_k f(R_k)``
    over each image's real rotations (NaN padding ignored); the same as the generic per-rotation mean,
    and the one-label loss when the set has one rotation."""
    from image2sphere.distributions.fourier import fourier_grid_nll, fourier_grid_set_nll
    from image2sphere.nn.base import mean_loss_over_set

    lmax, level = 3, 2
    torch.manual_seed(0)
    coeffs = torch.randn(3, n_so3_coeffs(lmax), dtype=torch.float64)
    R = haar_rotations(15, seed=4).reshape(3, 5, 3, 3)
    mask = torch.tensor([[1, 1, 1, 0, 0], [1, 0, 0, 0, 0], [1, 1, 1, 1, 1]], dtype=torch.bool)
    R = R.masked_fill(~mask[..., None, None], float("nan"))
    got = fourier_grid_set_nll(coeffs, lmax, R, mask, level)
    logits = reference_dense_grid_logits(coeffs, lmax, level)  # [B, N]
    lse = torch.logsumexp(logits, dim=1)
    grid = so3_healpix_index_to_matrix(torch.arange(logits.shape[1]), level, dtype=torch.float64)
    for b in range(3):
        index = brute_force_nearest(R[b][mask[b]], grid)
        assert got[b].item() == pytest.approx((lse[b] - logits[b, index].mean()).item(), rel=1e-10)
    generic = mean_loss_over_set(lambda o, r, lv: fourier_grid_nll(o, lmax, r, lv), coeffs, R, mask, level)
    torch.testing.assert_close(got, generic, rtol=1e-12, atol=1e-12)
    torch.testing.assert_close(got[1], fourier_grid_nll(coeffs[1:2], lmax, R[1, :1], level)[0])
    with pytest.raises(ValueError, match="at least one real rotation"):
        mean_loss_over_set(lambda o, r, lv: r.sum((1, 2)), coeffs, R, torch.zeros_like(mask), level)
    with pytest.raises(ValueError, match="must match"):
        mean_loss_over_set(lambda o, r, lv: r.sum((1, 2)), coeffs[:2], R, mask, level)
