"""Calibration of the density methods: highest-density-region (HDR) masses, coverage and ECE.

* The streamed masses above and tied with a query's grid point (one sweep, PoseDistribution.grid_summary)
  against a brute-force computation on the full grid: generic families (matrix Fisher, the piecewise-
  constant Euler bins), the Fourier fast path and the generic path on the same Fourier signal, over
  several chunks and every bucketing route of HdrMassAccumulator.
* Statistics: truths drawn from the predicted distribution itself give coverage alpha within binomial
  error; a too sharp (over-confident) prediction covers less, a too broad one more. Uniform and
  piecewise-constant densities are calibrated only thanks to the random tie-break.
* Symmetric objects: every real equivalent rotation counts as one (image, target) pair, padding never.
* The metrics plumbing: keys of the per-class summary, the tie-break seeds, the reliability diagram.
"""

from __future__ import annotations

import math

import pytest
import torch

import image2sphere.distributions.grid_protocol as grid_protocol
import image2sphere.so3.grid_eval as grid_eval
from conftest import brute_force_nearest, haar_rotations, reference_dense_grid_logits
from image2sphere.distributions import PointEstimate, PoseDistribution, SO3Distribution
from image2sphere.distributions.base import DensityNotAvailable
from image2sphere.distributions.euler_bins import EulerBins
from image2sphere.distributions.hdr_masses import HdrMassAccumulator
from image2sphere.distributions.matrix_fisher import MatrixFisher
from image2sphere.metrics import (
    HDR_COVERAGE_KEYS,
    HDR_LEVELS,
    density_pairs,
    hdr_coverage_counts,
    hdr_levels,
    hdr_levels_from_grid_logits,
    log_likelihood_pairs,
    summarize_pose_metrics,
    tie_break_uniforms,
)
from image2sphere.so3 import angles_to_matrix, so3_healpix_grid
from image2sphere.so3.wigner import n_so3_coeffs

ALPHAS = torch.tensor(HDR_LEVELS, dtype=torch.float64)


class GenericFourier(SO3Distribution):
    """The same Fourier signal through the base class's chunked sweep instead of the fast path."""

    _summary_sweep = PoseDistribution._summary_sweep
    _values_at_index = PoseDistribution._values_at_index


def fisher(n: int, kappa: float, seed: int) -> MatrixFisher:
    """``F = kappa * R`` with Haar-random ``R`` and a random anisotropy in ``[0.5, 1.5]`` per axis."""
    g = torch.Generator().manual_seed(seed)
    scale = 0.5 + torch.rand(n, 3, generator=g, dtype=torch.float64)
    return MatrixFisher(kappa * haar_rotations(n, seed=seed) * scale[:, None, :])


def fourier(n: int, lmax: int, scale: float, seed: int, cls=SO3Distribution) -> SO3Distribution:
    g = torch.Generator().manual_seed(seed)
    return cls(torch.randn(n, n_so3_coeffs(lmax), generator=g, dtype=torch.float64) * scale, lmax)


def euler_bins(n: int, num_bins: int, seed: int) -> EulerBins:
    g = torch.Generator().manual_seed(seed)
    return EulerBins(torch.randn(n, 3, num_bins, generator=g, dtype=torch.float64) * 1.5)


def brute_force_masses(values: torch.Tensor, index: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Masses above and tied (exact equality) from dense grid values ``(B, N)`` at indices ``(B, K)``,
    comparing every query with every grid point."""
    probs = torch.softmax(values.double(), dim=1)[:, None, :]  # [B, 1, N]
    own = values.gather(1, index)[..., None]  # [B, K, 1]
    above = (probs * (values[:, None, :] > own)).sum(-1)
    tied = (probs * (values[:, None, :] == own)).sum(-1)
    return above, tied


def queries(batch: int, k: int, seed: int) -> torch.Tensor:
    """``(B, K, 3, 3)`` rotations, with duplicates (ties between queries, crowded edges)."""
    R = haar_rotations(batch * k, seed=seed).reshape(batch, k, 3, 3)
    if k > 1:
        R[:, k // 2 :: 3] = R[:, :1].clone()  # every third of the second half equals the first query
    return R


KNOBS = {  # HdrMassAccumulator settings that force each bucketing route
    "default": {},
    "cell table for two edges": {"COMPARE_EDGES": 0},
    "every value bucketed": {"DENSE_FRACTION": 0.0},
    "crowded cells": {"DENSE_FRACTION": 1.0, "CELLS_PER_EDGE": 1, "COMPARE_EDGES": 1},
}


class VanishingFisher(MatrixFisher):
    """A matrix Fisher density set to zero (log density ``-inf``) where ``tr(F^T R) < 0``."""

    def unnormalized_log_density(self, rotations):
        values = super().unnormalized_log_density(rotations)
        return values.masked_fill(values < 0, -math.inf)


@pytest.mark.parametrize("knobs", list(KNOBS))
@pytest.mark.parametrize("family", ["matrix_fisher", "euler_bins", "fourier", "fourier_generic", "vanishing"])
@pytest.mark.parametrize("k", [1, 12])
def test_streamed_masses_equal_brute_force_on_the_full_grid(family, k, knobs, monkeypatch):
    level = 2
    monkeypatch.setattr(grid_protocol, "CHUNK_POINTS", 1000)  # 4608 points: 5 chunks, the last partial
    monkeypatch.setattr(grid_eval, "_CHUNK_ELEMENTS", 3000)  # fast path: 5 pixel chunks, the last partial
    for name, value in KNOBS[knobs].items():
        monkeypatch.setattr(HdrMassAccumulator, name, value)
    grid = so3_healpix_grid(level, dtype=torch.float64)
    if family == "matrix_fisher":
        dist = fisher(3, 8.0, seed=1)
        values = dist.unnormalized_log_density(grid)
    elif family == "euler_bins":
        dist = euler_bins(3, 4, seed=2)
        values = dist.unnormalized_log_density(grid)
    elif family == "vanishing":  # queries where the density is zero: edges at -inf, no cell table
        dist = VanishingFisher(fisher(3, 8.0, seed=1).F)
        values = dist.unnormalized_log_density(grid)
    else:
        dist = fourier(3, 3, 1.0, seed=3, cls=GenericFourier if family == "fourier_generic" else SO3Distribution)
        values = reference_dense_grid_logits(dist.coeffs, 3, level)
    R = queries(3, k, seed=4)
    summary = dist.grid_summary(level, R)
    index = brute_force_nearest(R.reshape(-1, 3, 3), grid).reshape(3, k)
    assert torch.equal(summary.index, index)
    above, tied = brute_force_masses(values, index)
    torch.testing.assert_close(summary.mass_above, above, rtol=0, atol=1e-12)
    torch.testing.assert_close(summary.mass_tied, tied, rtol=0, atol=1e-12)
    log_prob = torch.log_softmax(values, 1).gather(1, index)
    torch.testing.assert_close(summary.log_prob, log_prob, rtol=0, atol=1e-10)
    if family == "vanishing":
        assert (log_prob == -math.inf).any() and (k == 1 or (log_prob > -math.inf).any())
        assert torch.allclose(summary.mass_above[log_prob == -math.inf], torch.tensor(1.0, dtype=torch.float64))
    lse, top, arg = dist.grid_logsumexp_and_max(level)
    torch.testing.assert_close(summary.log_normalizer, lse, rtol=0, atol=1e-10)
    assert torch.equal(summary.argmax, arg)
    torch.testing.assert_close(summary.max, top, rtol=0, atol=1e-12)
    if family == "euler_bins":  # piecewise constant: whole boxes tie
        assert (tied > 10 * torch.softmax(values, 1).gather(1, index)).all()
    # the dense metrics reference agrees (u = 0.5: the middle of the tie)
    u = torch.full((3, k), 0.5, dtype=torch.float64)
    q = hdr_levels_from_grid_logits(values, R, None, level, u)
    torch.testing.assert_close(q, above + 0.5 * tied, rtol=0, atol=1e-12)


def test_summary_sweep_handles_chunks_where_the_density_vanishes(monkeypatch):
    """Whole chunks of -inf next to values far below 0: the log normaliser of the summary's sweep (made
    from its exponentials) equals the dense one."""

    class FarBelow(MatrixFisher):
        def unnormalized_log_density(self, rotations):
            values = super().unnormalized_log_density(rotations)
            return (values - 1000).masked_fill(values < 0, -math.inf)

    monkeypatch.setattr(grid_protocol, "CHUNK_POINTS", 200)  # many chunks, some wholly -inf
    dist = FarBelow(10 * torch.eye(3, dtype=torch.float64).expand(2, 3, 3))
    values = dist.unnormalized_log_density(so3_healpix_grid(2, torch.float64))
    chunks = values.split(192, dim=1)
    assert any((c == -math.inf).all() for c in chunks) and all(c.max() > -math.inf for c in values)
    summary = dist.grid_summary(2, haar_rotations(2, seed=20)[:, None])
    torch.testing.assert_close(summary.log_normalizer, torch.logsumexp(values, 1), rtol=0, atol=1e-9)


@pytest.mark.parametrize("knobs", list(KNOBS))
def test_accumulator_takes_chunks_of_any_size_in_any_order(knobs, monkeypatch):
    """Values fed directly: loose chunks (groups of consecutive points and a ragged tail) and chunks of
    whole fibres whose pixel count is no multiple of the group, one of them all -inf, in shuffled order."""
    for name, value in KNOBS[knobs].items():
        monkeypatch.setattr(HdrMassAccumulator, name, value)
    g = torch.Generator().manual_seed(19)
    B, P, G, K = 3, 64, 6, 7
    values = torch.randn(B, P * G, generator=g, dtype=torch.float64).cumsum(1) * 0.3  # smooth-ish, with ties:
    values[:, 100:130] = values[:, 100:101]
    values[:, 53 * G : 56 * G] = -math.inf  # a chunk of fibres where the density vanishes
    index = torch.randint(0, P * G, (B, K), generator=g)
    index[(index >= 53 * G) & (index < 56 * G)] = 0
    index[:, 0] = 110  # a query in the tied stretch
    accumulator = HdrMassAccumulator(values.gather(1, index), index)
    pieces = [(0, 37), (37, 103), (103, 120), (120, 156), (156, 240)]  # loose: 37 = 2 * 16 + 5 ...
    fibres = [(40, 53), (56, 64)]  # pixels: 13 and 8 of them (whole fibres of G = 6)
    order = [("fibres", *f) for f in fibres] + [("loose", *p) for p in pieces]
    order = [("fibres", 53, 56)] + [order[i] for i in torch.randperm(len(order), generator=g).tolist()]
    for kind, a, b in order:  # the vanishing chunk first
        if kind == "loose":
            accumulator.add(values[:, a:b], a)
        else:
            chunk = values[:, a * G : b * G].reshape(B, b - a, G)
            reference = chunk.amax(dim=(1, 2))
            accumulator.add_fibres(chunk, torch.exp(chunk - reference[:, None, None]), reference, a)
    above, tied = accumulator.masses(torch.logsumexp(values, dim=1))
    expected_above, expected_tied = brute_force_masses(values, index)
    torch.testing.assert_close(above, expected_above, rtol=0, atol=1e-12)
    torch.testing.assert_close(tied, expected_tied, rtol=0, atol=1e-12)
    assert (expected_tied[:, 0] >= 30 * torch.softmax(values, 1)[:, 110]).all()


@pytest.mark.parametrize("offset", [-1e-7, 1e-7])
def test_the_query_point_is_tied_with_itself_even_when_its_two_values_disagree(offset, monkeypatch):
    """The value read at a query and the sweep's value at its grid point come from two computations; here
    they differ by far more than the tie tolerance. The point itself still counts as tied, not above or
    below, and the other points are classified as on the full grid."""

    class Disagreeing(MatrixFisher):
        def _values_at_index(self, index, level):
            return super()._values_at_index(index, level) + offset

    monkeypatch.setattr(grid_protocol, "CHUNK_POINTS", 1000)
    dist = Disagreeing(fisher(3, 8.0, seed=1).F)
    R = queries(3, 12, seed=18)
    summary = dist.grid_summary(2, R)
    above, tied = brute_force_masses(dist.unnormalized_log_density(so3_healpix_grid(2, torch.float64)), summary.index)
    torch.testing.assert_close(summary.mass_above, above, rtol=0, atol=1e-12)
    torch.testing.assert_close(summary.mass_tied, tied, rtol=0, atol=1e-12)


def test_fast_path_float32_at_level_3_matches_the_dense_reference_and_ties_each_query_with_itself():
    """float32: the query's value (read at the point) and the sweep's differ in the last bits; the point
    itself still counts as tied, and the masses match a float64 dense computation to float32 accuracy."""
    dist = fourier(4, 6, 3.0, seed=5)  # large signal: the two computations differ by ~100 eps
    dist32 = SO3Distribution(dist.coeffs.float(), 6)
    R = dist32.sample(30, 3, generator=torch.Generator().manual_seed(6))  # [4, 30, 3, 3]: where the mass is
    summary = dist32.grid_summary(3, R)
    values = dist.grid_logits(3)  # float64
    above, tied = brute_force_masses(values, summary.index)
    p_own = torch.softmax(values, 1).gather(1, summary.index)
    assert (summary.mass_tied >= p_own * (1 - 1e-3)).all()
    torch.testing.assert_close(summary.mass_above, above, rtol=0, atol=2e-5)
    torch.testing.assert_close(summary.mass_tied, tied, rtol=0, atol=2e-5)


# ------------------------------------------------------------------ calibration statistics
def coverage(dist: PoseDistribution, truths: torch.Tensor, level: int, u: torch.Tensor | None = None) -> torch.Tensor:
    """Fraction of the truths ``(B, M, 3, 3)`` inside the HDR of each mass of HDR_LEVELS: ``(9,)``."""
    if u is None:
        u = torch.rand(truths.shape[:2], generator=torch.Generator().manual_seed(7), dtype=torch.float64)
    pairs = density_pairs(dist, truths, None, level, u)
    return hdr_coverage_counts(pairs.hdr_level).sum(0).double() / pairs.hdr_level.numel()


def binomial_sigma(n: int) -> torch.Tensor:
    return torch.sqrt(ALPHAS * (1 - ALPHAS) / n)


def assert_calibrated(cov: torch.Tensor, n: int) -> None:
    assert ((cov - ALPHAS).abs() <= 4 * binomial_sigma(n)).all(), cov
    assert float((cov - ALPHAS).abs().mean()) < 0.05, cov


@pytest.mark.parametrize("family", ["matrix_fisher", "fourier"])
def test_truths_drawn_from_the_prediction_are_covered_at_the_nominal_rate(family):
    n, level = 500, 2
    if family == "matrix_fisher":
        dist, broad, sharp = fisher(n, 10.0, seed=8), None, None
        broad, sharp = MatrixFisher(dist.F / 4), MatrixFisher(dist.F * 4)
    else:
        dist = fourier(n, 4, 0.6, seed=9)
        broad, sharp = SO3Distribution(dist.coeffs / 3, 4), SO3Distribution(dist.coeffs * 3, 4)
    g = torch.Generator().manual_seed(10)
    assert_calibrated(coverage(dist, dist.sample(1, level, generator=g), level), n)
    # over-confident: the truths come from a broader distribution than predicted
    over = coverage(dist, broad.sample(1, level, generator=g), level)
    assert (over < ALPHAS - 5 * binomial_sigma(n)).all() and float((over - ALPHAS).abs().mean()) > 0.15, over
    # under-confident: the truths come from a sharper one
    under = coverage(dist, sharp.sample(1, level, generator=g), level)
    assert (under > ALPHAS + 5 * binomial_sigma(n)).all() and float((under - ALPHAS).abs().mean()) > 0.15, under


@pytest.mark.parametrize("family", ["uniform", "euler_bins"])
def test_flat_and_piecewise_constant_densities_are_calibrated_thanks_to_the_tie_break(family):
    n, level = 500, 2
    dist = MatrixFisher(torch.zeros(n, 3, 3, dtype=torch.float64)) if family == "uniform" else euler_bins(n, 3, 11)
    truths = dist.sample(1, level, generator=torch.Generator().manual_seed(12))
    assert_calibrated(coverage(dist, truths, level), n)
    # without the tie-break (u = 0) every truth would lie at the bottom of its tie: too often inside
    ties_first = coverage(dist, truths, level, u=torch.zeros(n, 1, dtype=torch.float64))
    assert (ties_first > ALPHAS).all() and (ties_first - ALPHAS > 6 * binomial_sigma(n)).any(), ties_first


# ------------------------------------------------------------------ symmetric objects
def about_y(angle: float) -> torch.Tensor:
    return angles_to_matrix(torch.tensor(0.0), torch.tensor(0.0), torch.tensor(angle)).double()


def test_every_real_equivalent_rotation_is_one_pair_and_padding_never_counts():
    """A density peaked at the identity: the identity lies inside every HDR of mass >= 0.2, a rotation by
    180 degrees outside every one. Per pair, 3 of the 6 real pairs are inside (0.5); the mean of the
    images' fractions would be 0.61 and "any equivalent inside" 1.0."""
    eye, flip = torch.eye(3, dtype=torch.float64), about_y(math.pi)
    other = torch.tensor([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]], dtype=torch.float64)  # 180 degrees about x
    nan = torch.full((3, 3), math.nan, dtype=torch.float64)
    targets = torch.stack([
        torch.stack([eye, eye, eye, eye]),  # 1 real: inside; its padding would be inside too
        torch.stack([eye, flip, other, nan]),  # 3 real: 1 inside; padding NaN
        torch.stack([flip, eye, nan, nan]),  # 2 real: 1 inside
    ])  # fmt: skip
    mask = torch.tensor([[1, 0, 0, 0], [1, 1, 1, 0], [1, 1, 0, 0]], dtype=torch.bool)
    dist = MatrixFisher(10 * torch.eye(3, dtype=torch.float64).expand(3, 3, 3))
    u = tie_break_uniforms([0, 1, 2], 4)
    pairs = density_pairs(dist, targets, mask, 3, u)
    assert torch.isnan(pairs.hdr_level[~mask]).all() and not torch.isnan(pairs.hdr_level[mask]).any()
    torch.testing.assert_close(pairs.log_density, log_likelihood_pairs(dist, targets, mask, 3), equal_nan=True)
    counts = hdr_coverage_counts(pairs.hdr_level, mask)  # [3, 9]
    assert counts[:, 1:].tolist() == [[1] * 8, [1] * 8, [1] * 8]
    metrics = summarize_pose_metrics(
        torch.zeros(3, dtype=torch.long), ["shape"], error_deg=torch.zeros(3), ll_sum=torch.zeros(3),
        ll_count=mask.sum(1), hdr_counts=counts,
    )  # fmt: skip
    for key in HDR_COVERAGE_KEYS[1:]:
        assert metrics[key] == metrics[f"{key}/shape"] == 0.5, (key, metrics[key])
    expected_ece = float((torch.tensor([metrics[k] for k in HDR_COVERAGE_KEYS]) - ALPHAS).abs().mean())
    assert metrics["calibration_ece"] == pytest.approx(expected_ece)


def test_a_unimodal_prediction_of_a_symmetric_object_is_over_confident_per_pair_but_not_by_any_inside():
    """Truths drawn from a unimodal prediction; the object has a second, equivalent pose 180 degrees away
    that the prediction ignores. Per pair the coverage is alpha / 2 (it misses half of the pose set);
    counting an image as covered when any equivalent is inside would report alpha: calibrated."""
    n, level = 500, 2
    dist = fisher(n, 10.0, seed=13)
    truth = dist.sample(1, level, generator=torch.Generator().manual_seed(14))  # [n, 1, 3, 3]
    targets = torch.cat([truth, truth @ about_y(math.pi)], dim=1)  # [n, 2, 3, 3]
    u = torch.rand(n, 2, generator=torch.Generator().manual_seed(15), dtype=torch.float64)
    q = density_pairs(dist, targets, None, level, u).hdr_level  # [n, 2]
    per_pair = hdr_coverage_counts(q).sum(0).double() / q.numel()
    assert ((per_pair - ALPHAS / 2).abs() <= 4 * torch.sqrt(ALPHAS * (1 - ALPHAS) / n) / 2).all(), per_pair
    any_inside = (q.min(dim=1).values[:, None] < ALPHAS).double().mean(0)
    assert ((any_inside - ALPHAS).abs() <= 4 * binomial_sigma(n)).all(), any_inside


# ------------------------------------------------------------------ plumbing
def test_summary_has_calibration_keys_only_for_densities():
    class_index = torch.tensor([0, 0, 1])
    counts = torch.tensor([[0, 1, 1, 1, 1, 1, 1, 2, 2], [0] * 9, [1] * 9])
    density = summarize_pose_metrics(class_index, ["a", "b"], error_deg=torch.zeros(3), ll_sum=torch.zeros(3),
                                     ll_count=torch.tensor([2, 1, 1]), hdr_counts=counts)  # fmt: skip
    assert density["hdr_coverage_80/a"] == pytest.approx(2 / 3) and density["hdr_coverage_10/b"] == 1.0
    assert density["hdr_coverage_80"] == pytest.approx((2 / 3 + 1) / 2)  # the mean over classes
    ece_a = float((torch.tensor([0, 1, 1, 1, 1, 1, 1, 2, 2]) / 3 - ALPHAS).abs().mean())
    assert density["calibration_ece/a"] == pytest.approx(ece_a)
    assert density["calibration_ece"] == pytest.approx((ece_a + float((1 - ALPHAS).mean())) / 2)
    point = summarize_pose_metrics(class_index, ["a", "b"], error_deg=torch.zeros(3))
    assert not [k for k in point if k.startswith(("hdr_coverage", "calibration_ece"))]
    with pytest.raises(DensityNotAvailable):
        PointEstimate(torch.eye(3).expand(2, 3, 3)).grid_summary(2, torch.eye(3).expand(2, 1, 3, 3))


def test_hdr_level_definition_and_shape_errors():
    above = torch.tensor([[0.2, 0.0]], dtype=torch.float64)
    tied = torch.tensor([[0.1, 1.0]], dtype=torch.float64)
    q = hdr_levels(above, tied, torch.tensor([[0.5, 0.25]]))
    assert q.tolist() == [[0.25, 0.25]]
    with pytest.raises(ValueError, match=r"one shape, got \(1, 2\), \(1, 2\) and \(2,\)"):
        hdr_levels(above, tied, torch.zeros(2))
    dist = fisher(2, 5.0, seed=16)
    with pytest.raises(ValueError, match=r"B = batch size 2, got \(3, 1, 3, 3\)"):
        dist.grid_summary(2, haar_rotations(3).reshape(3, 1, 3, 3))
    with pytest.raises(ValueError, match=r"u must have the shape of mask \(2, 1\), got \(2, 2\)"):
        density_pairs(dist, haar_rotations(2).reshape(2, 1, 3, 3), None, 2, torch.zeros(2, 2))
    with pytest.raises(ValueError, match=r"one shape \(B, K\), got \(4,\) and \(4,\)"):
        HdrMassAccumulator(torch.zeros(4), torch.zeros(4, dtype=torch.long))
    with pytest.raises(ValueError, match=r"hdr_level must have shape \(B, M\), got \(5,\)"):
        hdr_coverage_counts(torch.zeros(5))
    # a shared query set (K, 3, 3) is the same as repeating it per distribution
    R = haar_rotations(4, seed=17)
    shared, batched = dist.hdr_masses(R, 2), dist.hdr_masses(R.expand(2, 4, 3, 3), 2)
    torch.testing.assert_close(shared, batched, rtol=0, atol=1e-12)


def test_tie_break_draws_depend_only_on_the_seed():
    a = tie_break_uniforms([3, 1, 3], 5)
    assert torch.equal(a[0], a[2]) and not torch.equal(a[0], a[1])
    assert torch.equal(tie_break_uniforms([1], 2)[0], a[1, :2])  # fewer targets: a prefix of the same draws
    assert ((a >= 0) & (a < 1)).all() and a.dtype == torch.float64


def test_reliability_diagram_draws_each_class_the_mean_and_the_diagonal():
    from image2sphere.plot import plot_reliability

    metrics = {"calibration_ece": 0.1, "calibration_ece/a": 0.05, "calibration_ece/b": 0.15}
    for key, alpha in zip(HDR_COVERAGE_KEYS, HDR_LEVELS, strict=True):
        metrics[key], metrics[f"{key}/a"], metrics[f"{key}/b"] = alpha * 0.9, alpha, alpha * 0.8
    fig = plot_reliability(metrics, ["a", "b", "absent"], title="t")
    lines = fig.axes[0].get_lines()
    assert len(lines) == 4  # diagonal, two classes, mean
    assert list(lines[-1].get_ydata()) == pytest.approx([a * 0.9 for a in HDR_LEVELS])
    labels = [t.get_text() for t in fig.axes[0].get_legend().get_texts()]
    assert labels == ["calibrated", "a (ECE 0.050)", "b (ECE 0.150)", "mean over classes (ECE 0.100)"]
    with pytest.raises(ValueError, match="no calibration"):
        plot_reliability({"acc15": 0.5}, ["a"])
