"""Pose metrics (docs/evaluation.md) against analytic values, dense references and scipy."""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import haar_rotations
from image2sphere.distributions import LOG_UNIFORM_DENSITY, SO3Distribution
from image2sphere.metrics import (
    check_target_mask,
    check_targets,
    log_density_from_grid_logits,
    log_likelihood_pairs,
    min_angular_error_deg,
    spread_deg,
    summarize_pose_metrics,
)
from image2sphere.rotation_sets import check_rotation_set
from image2sphere.so3 import (
    dense_grid_logits,
    n_so3_coeffs,
    so3_grid_size,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)

LEVEL = 2


def _n(level: int) -> int:
    return math.prod(so3_grid_size(level))


def test_uniform_logits_give_log_uniform_density():
    targets = haar_rotations(6, seed=1).reshape(2, 3, 3, 3)
    ll = log_density_from_grid_logits(torch.zeros(2, _n(LEVEL), dtype=torch.float64), targets, None, LEVEL)
    torch.testing.assert_close(ll, torch.full((2, 3), LOG_UNIFORM_DENSITY, dtype=torch.float64))
    assert LOG_UNIFORM_DENSITY == pytest.approx(-2.2894, abs=1e-4)


def test_peak_at_label_gives_log_n_over_pi_squared():
    targets = haar_rotations(4, seed=2)[:, None]  # [B, 1, 3, 3]
    index = so3_healpix_nearest_index(targets[:, 0], LEVEL)
    logits = torch.zeros(4, _n(LEVEL), dtype=torch.float64)
    logits[torch.arange(4), index] = 1e4
    ll = log_density_from_grid_logits(logits, targets, None, LEVEL)
    expected = math.log(_n(LEVEL) / math.pi**2)
    torch.testing.assert_close(ll[:, 0], torch.full((4,), expected, dtype=torch.float64))
    # a rotation far from the peak gets (almost) nothing
    far = targets @ torch.tensor(Rotation.from_euler("x", 90, degrees=True).as_matrix())
    assert (log_density_from_grid_logits(logits, far, None, LEVEL) < -1000).all()


def test_streamed_log_likelihood_matches_dense_reference_and_masks_padding():
    torch.manual_seed(0)
    lmax = 3
    coeffs = torch.randn(3, n_so3_coeffs(lmax), dtype=torch.float64)
    targets = haar_rotations(12, seed=3).reshape(3, 4, 3, 3).clone()
    mask = torch.tensor([[1, 1, 1, 1], [1, 0, 0, 0], [1, 1, 0, 0]], dtype=torch.bool)
    targets[~mask] = math.nan  # NaN padding must not leak into the result
    dist = SO3Distribution(coeffs, lmax)
    fast = log_likelihood_pairs(dist, targets, mask, LEVEL)
    dense = log_density_from_grid_logits(dense_grid_logits(coeffs, lmax, LEVEL), targets, mask, LEVEL)
    assert torch.isnan(fast[~mask]).all() and torch.isnan(dense[~mask]).all()
    torch.testing.assert_close(fast[mask], dense[mask])
    # a log-normaliser computed elsewhere (e.g. with the argmax) gives the same values
    given = log_likelihood_pairs(dist, targets, mask, LEVEL, log_normalizer=dist.log_normalizer(LEVEL))
    torch.testing.assert_close(given[mask], fast[mask])


def test_min_angular_error_against_scipy_and_mask():
    pred = haar_rotations(5, seed=4)
    targets = haar_rotations(15, seed=5).reshape(5, 3, 3, 3)
    mask = torch.ones(5, 3, dtype=torch.bool)
    mask[0, 1:] = False
    err = min_angular_error_deg(pred, targets, mask)
    for b in range(5):
        angles = [
            Rotation.from_matrix((pred[b].T @ targets[b, j]).numpy()).magnitude() * 180 / math.pi
            for j in range(3)
            if mask[b, j]
        ]
        assert err[b].item() == pytest.approx(min(angles), abs=1e-6)


def test_spread_of_uniform_is_mean_haar_angle():
    # For a single ground truth, the Haar-mean angle is pi/2 + 2/pi radians (126.48 deg): the angle
    # density is (1 - cos t) / pi on [0, pi].
    lmax = 2
    targets = haar_rotations(2, seed=6)[:, None]
    dist = SO3Distribution(torch.zeros(2, n_so3_coeffs(lmax), dtype=torch.float64), lmax)
    expected = math.degrees(math.pi / 2 + 2 / math.pi)
    torch.testing.assert_close(
        spread_deg(dist, targets, None, 3), torch.full((2,), expected, dtype=torch.float64), atol=0.3, rtol=0
    )


def test_spread_against_dense_sum_with_symmetric_targets():
    torch.manual_seed(1)
    lmax = 3
    coeffs = 3 * torch.randn(2, n_so3_coeffs(lmax), dtype=torch.float64)
    targets = haar_rotations(8, seed=7).reshape(2, 4, 3, 3)
    mask = torch.tensor([[1, 1, 1, 0], [1, 1, 1, 1]], dtype=torch.bool)
    got = spread_deg(SO3Distribution(coeffs, lmax), targets, mask, LEVEL, max_pairs=1000)  # many blocks
    p = torch.softmax(dense_grid_logits(coeffs, lmax, LEVEL), dim=1)  # [B, N]
    grid = so3_healpix_index_to_matrix(torch.arange(_n(LEVEL)), LEVEL, dtype=torch.float64)  # [N, 3, 3]
    for b in range(2):
        rel = grid[:, None].transpose(-1, -2) @ targets[b][mask[b]][None]  # [N, m, 3, 3]
        angle = Rotation.from_matrix(rel.reshape(-1, 3, 3).numpy()).magnitude().reshape(len(grid), -1).min(1)
        assert got[b].item() == pytest.approx(float((p[b] * torch.as_tensor(angle)).sum()) * 180 / math.pi, rel=1e-6)


def test_summary_per_class_and_mean_over_classes():
    class_index = torch.tensor([0, 0, 0, 1, 1])
    error = torch.tensor([10.0, 20.0, 40.0, 5.0, 35.0])
    ll_sum = torch.tensor([1.0, 2.0, 3.0, 10.0, 20.0])
    ll_count = torch.tensor([1, 1, 1, 2, 8])
    m = summarize_pose_metrics(class_index, ["a", "b"], error, ll_sum, ll_count)
    assert m["acc15/a"] == pytest.approx(1 / 3) and m["acc30/a"] == pytest.approx(2 / 3)
    assert m["acc15/b"] == pytest.approx(1 / 2) and m["acc30/b"] == pytest.approx(1 / 2)
    assert m["median_error_deg/a"] == 20.0 and m["median_error_deg/b"] == 20.0
    # the mean of the per-image means (b: 10/2 and 20/8), not the mean over all pairs (30/10)
    assert m["log_likelihood/a"] == pytest.approx(2.0) and m["log_likelihood/b"] == pytest.approx(3.75)
    assert m["log_likelihood"] == pytest.approx(2.875) and m["acc15"] == pytest.approx((1 / 3 + 1 / 2) / 2)
    assert m["n_images"] == 5


@pytest.mark.parametrize(
    "targets, mask, match",
    [
        (torch.eye(3).expand(2, 3, 3), None, "targets must have shape"),
        (torch.eye(3).expand(2, 1, 3, 3), torch.ones(2, 2, dtype=torch.bool), "mask must be bool"),
        (torch.eye(3).expand(2, 2, 3, 3), torch.tensor([[0, 1], [1, 1]], dtype=torch.bool), r"mask\[:, 0\]"),
    ],
)
def test_bad_targets_are_rejected(targets, mask, match):
    with pytest.raises(ValueError, match=match):
        min_angular_error_deg(torch.eye(3).expand(2, 3, 3), targets, mask)


def test_metrics_and_set_losses_check_the_padding_by_one_rule():
    """:func:`check_target_mask` is the rule of both :func:`check_targets` (metrics) and
    :func:`check_rotation_set` (set losses): the masks the loaders build pass (SYMSOL's ``arange(M) < count``,
    all True for one-label sets), and a set whose first entry is padding is refused by both with the same
    message even when a later entry is real (``fill_padding`` would read the padding as the image's rotation)."""
    targets = haar_rotations(12, seed=3).reshape(3, 4, 3, 3)
    output = torch.zeros(3, 5)
    symsol = torch.arange(4) < torch.tensor([1, 3, 4])[:, None]  # [3, 4]
    for mask in (symsol, torch.ones(3, 4, dtype=torch.bool)):
        assert check_targets(targets, mask, 3) is mask
        check_rotation_set(output, targets, mask)
    checks = (
        check_target_mask,
        lambda m: check_targets(targets, m, 3),
        lambda m: check_rotation_set(output, targets, m),
    )
    for check in checks:
        with pytest.raises(ValueError, match=r"mask\[:, 0\] must be True"):
            check(symsol.flip(1))  # the real rotations after the padding
        with pytest.raises(ValueError, match="at least one real rotation"):
            check(torch.zeros(3, 4, dtype=torch.bool))
