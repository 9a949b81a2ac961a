"""Pose metrics (docs/evaluation.md), per image and summarised per class.

Conventions
-----------
* Ground truth is a padded set of equivalent rotations per image: ``targets (B, M, 3, 3)`` with a
  boolean ``mask (B, M)`` marking the real entries (a symmetric object has several rotations that
  give the same image; an asymmetric one has ``M = 1``). ``targets[:, 0]`` is always real
  (:func:`~image2sphere.rotation_sets.check_target_mask`).
* Angular error of a point estimate: the geodesic angle to the nearest equivalent rotation, in
  degrees. Acc@t is the fraction of images with error <= t degrees.
* Log likelihood: the model's log density (Haar measure of volume pi^2, read at the grid point
  nearest the rotation, :meth:`SO3Distribution.log_density`) at every real (image, equivalent
  rotation) pair, averaged over the image's set first: a class's value is the mean over its images of
  each image's mean, so every image weighs the same whatever the size of its set (the paper's
  protocol: the expectation of its code's one equivalent rotation drawn per image, and IPDF's mean
  over all pairs wherever a class's sets have one size). Uniform gives -log(pi^2) = -2.29.
* Spread: ``sum_i p_i * min_j angle(R_i, R_gt_j)`` in degrees over the grid of a level, with ``p``
  the grid softmax: how far (on average) the probability mass lies from the nearest ground truth.
* Calibration (docs/evaluation.md#calibration): the highest-density-region (HDR) level of a true
  rotation ``R`` with nearest grid point ``t`` is ``q = sum_{p_i > p_t} p_i + u * sum_{p_i == p_t} p_i``
  (``u ~ Uniform(0, 1)``, a fixed draw per (image, target) pair: ties broken at random, so that ``q`` is
  exactly uniform for a calibrated predictor, flat densities included). The truth lies in the HDR of
  mass ``alpha`` iff ``q < alpha``. Coverage at ``alpha`` (:data:`HDR_LEVELS`): the fraction of a class's
  real (image, target) pairs with ``q < alpha`` (every equivalent rotation an equally likely truth,
  each pair weighing the same); ECE: the mean over the levels of ``|coverage - alpha|``.
* Headline numbers are means over classes of the per-class values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import NamedTuple

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.data.common import stable_seed
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY, PoseDistribution
from image2sphere.distributions.hdr_masses import tie_tolerance
from image2sphere.precision import constant_cache
from image2sphere.rotation_sets import check_target_mask, check_targets, fill_padding
from image2sphere.so3.grid import check_level, so3_grid_size, so3_healpix_grid, so3_healpix_nearest_index
from image2sphere.so3.rotations import geodesic_distance_deg

__all__ = [
    "ACC_THRESHOLDS_DEG",
    "HDR_COVERAGE_KEYS",
    "HDR_LEVELS",
    "DensityPairs",
    "check_target_mask",
    "check_targets",
    "density_pairs",
    "hdr_coverage_counts",
    "hdr_levels",
    "hdr_levels_from_grid_logits",
    "log_density_from_grid_logits",
    "log_likelihood_pairs",
    "min_angular_error_deg",
    "spread_deg",
    "summarize_pose_metrics",
    "tie_break_uniforms",
]

ACC_THRESHOLDS_DEG = (15.0, 30.0)
#: nominal masses ``alpha`` of the highest-density regions whose coverage is reported
HDR_LEVELS = (0.1, 0.2, 0.3, 0.4, 0.5, 0.6, 0.7, 0.8, 0.9)
#: the metric key of each level's coverage: ``hdr_coverage_10`` ... ``hdr_coverage_90``
HDR_COVERAGE_KEYS = tuple(f"hdr_coverage_{round(100 * a)}" for a in HDR_LEVELS)


def min_angular_error_deg(pred: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Angle ``(B,)`` in degrees from ``pred (B, 3, 3)`` to the nearest real target."""
    if pred.ndim != 3 or pred.shape[-2:] != (3, 3):
        raise ConfigError(f"pred must have shape (B, 3, 3), got {tuple(pred.shape)}")
    mask = check_targets(targets, mask, len(pred))
    err = geodesic_distance_deg(pred[:, None].to(targets.dtype), targets)  # [B, M]
    return err.masked_fill(~mask, math.inf).min(dim=1).values


def log_likelihood_pairs(
    dist: PoseDistribution,
    targets: torch.Tensor,
    mask: torch.Tensor | None,
    level: int,
    log_normalizer: torch.Tensor | None = None,
) -> torch.Tensor:
    """Log density at every (image, target) pair: ``(B, M)``, NaN where ``mask`` is False.

    ``log_normalizer`` ``(B,)``: the grid's logsumexp at ``level`` when already computed.
    """
    mask = check_targets(targets, mask, dist.batch_size)
    ll = dist.log_density(fill_padding(targets, mask), level, log_normalizer)  # [B, M]
    return ll.masked_fill(~mask, math.nan)


def _check_grid_logits(grid_logits: torch.Tensor, level: int) -> tuple[int, int]:
    """``(level, number of grid points)``; ``ValueError`` unless ``grid_logits`` is ``(B, N)`` for ``level``."""
    level = check_level(level)
    n_points = math.prod(so3_grid_size(level))
    if grid_logits.ndim != 2 or grid_logits.shape[1] != n_points:
        raise ConfigError(
            f"grid_logits must have shape (B, {n_points}) for level {level}, got {tuple(grid_logits.shape)}"
        )
    return level, n_points


def log_density_from_grid_logits(
    grid_logits: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None, level: int
) -> torch.Tensor:
    """Log density ``(B, M)`` (NaN where masked) from dense logits ``(B, N)`` on the grid of ``level``.

    ``log_softmax(logits)[nearest(R)] + log(N / pi^2)``: the dense reference of the streamed path
    (:meth:`SO3Distribution.log_density`), usable with any hand-made or externally computed logits.
    """
    level, n_points = _check_grid_logits(grid_logits, level)
    mask = check_targets(targets, mask, len(grid_logits))
    index = so3_healpix_nearest_index(fill_padding(targets, mask), level).to(grid_logits.device)  # [B, M]
    log_p = torch.log_softmax(grid_logits, dim=1).gather(1, index)  # [B, M]
    return (log_p + math.log(n_points) + LOG_UNIFORM_DENSITY).masked_fill(~mask, math.nan)


def hdr_levels(mass_above: torch.Tensor, mass_tied: torch.Tensor, u: torch.Tensor) -> torch.Tensor:
    """HDR level ``q = mass_above + u * mass_tied`` (all of one shape, e.g. ``(B, M)``), float64 in ``[0, 1]``.

    ``mass_above``, ``mass_tied``: :meth:`PoseDistribution.hdr_masses`; ``u``: uniforms in ``[0, 1)``
    (:func:`tie_break_uniforms`). The truth lies in the highest-density region of mass ``alpha`` iff
    ``q < alpha``.
    """
    if not (mass_above.shape == mass_tied.shape == u.shape):
        raise ConfigError(
            f"mass_above, mass_tied and u must have one shape, got {tuple(mass_above.shape)}, "
            f"{tuple(mass_tied.shape)} and {tuple(u.shape)}"
        )
    u = u.to(device=mass_above.device, dtype=torch.float64)
    return (mass_above.double() + u * mass_tied.double()).clamp(0.0, 1.0)


def tie_break_uniforms(seeds: Sequence[int], m: int) -> torch.Tensor:
    """``u ~ Uniform(0, 1)`` for ``m`` targets of each image: ``(len(seeds), m)`` float64 on the CPU.

    Row ``i`` depends only on ``seeds[i]`` (and a row of ``m`` is a prefix of a longer one), so an image
    gets the same draws in every run, batch composition and process (the test loop seeds with the
    image's class and dataset index, :func:`stable_seed`).
    """
    check_int("m", m, 0)
    out = torch.empty(len(seeds), m, dtype=torch.float64)
    for i, seed in enumerate(seeds):
        generator = torch.Generator().manual_seed(stable_seed("hdr-tie-break", int(seed)))
        out[i] = torch.rand(m, generator=generator, dtype=torch.float64)
    return out


class DensityPairs(NamedTuple):
    """The density metrics of every (image, target) pair from one sweep (:func:`density_pairs`).

    ``log_density`` ``(B, M)``: as :func:`log_likelihood_pairs`; ``hdr_level`` ``(B, M)`` float64: the HDR
    level ``q`` (:func:`hdr_levels`); both NaN where ``mask`` is False. ``log_normalizer`` and ``argmax``
    ``(B,)``: the grid's logsumexp and the pixel-major index of its maximum (the point estimate).
    """

    log_density: torch.Tensor
    hdr_level: torch.Tensor
    log_normalizer: torch.Tensor
    argmax: torch.Tensor


def density_pairs(
    dist: PoseDistribution, targets: torch.Tensor, mask: torch.Tensor | None, level: int, u: torch.Tensor
) -> DensityPairs:
    """Log density and HDR level at every (image, target) pair, the grid's log normaliser and argmax,
    all from one streamed sweep of the grid of ``level`` (:meth:`PoseDistribution.grid_summary`).

    ``targets (B, M, 3, 3)``, ``mask (B, M)`` as in :func:`check_targets`; ``u (B, M)``: the tie-break
    uniforms (:func:`tie_break_uniforms`). ``log_density`` equals :func:`log_likelihood_pairs`.
    """
    mask = check_targets(targets, mask, dist.batch_size)
    if u.shape != mask.shape:
        raise ConfigError(f"u must have the shape of mask {tuple(mask.shape)}, got {tuple(u.shape)}")
    summary = dist.grid_summary(level, fill_padding(targets, mask))
    n_points = math.prod(so3_grid_size(level))
    log_density = summary.log_prob + math.log(n_points) + LOG_UNIFORM_DENSITY  # [B, M]
    q = hdr_levels(summary.mass_above, summary.mass_tied, u)  # [B, M]
    mask = mask.to(log_density.device)
    return DensityPairs(
        log_density.masked_fill(~mask, math.nan),
        q.masked_fill(~mask, math.nan),
        summary.log_normalizer,
        summary.argmax,
    )


def hdr_levels_from_grid_logits(
    grid_logits: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None, level: int, u: torch.Tensor
) -> torch.Tensor:
    """HDR levels ``(B, M)`` (NaN where masked) from dense logits ``(B, N)`` on the grid of ``level``.

    The dense reference of the streamed path (:func:`density_pairs`): with ``v`` the logit at the grid
    point nearest a target, the masses of the points with logit ``> v + tol`` and within ``tol`` of ``v``
    (:func:`~image2sphere.distributions.hdr_masses.tie_tolerance`), combined by :func:`hdr_levels`.
    Builds a ``(B, M, N)`` comparison: small grids only.
    """
    level, n_points = _check_grid_logits(grid_logits, level)
    mask = check_targets(targets, mask, len(grid_logits))
    if u.shape != mask.shape:
        raise ConfigError(f"u must have the shape of mask {tuple(mask.shape)}, got {tuple(u.shape)}")
    index = so3_healpix_nearest_index(fill_padding(targets, mask), level).to(grid_logits.device)  # [B, M]
    value = grid_logits.gather(1, index)  # [B, M]
    tol = torch.where(torch.isfinite(value), tie_tolerance(value), torch.zeros_like(value))
    low, high = (value - tol)[..., None], (value + tol)[..., None]  # [B, M, 1]: the band of ties
    probs = torch.softmax(grid_logits.double(), dim=1)[:, None, :]  # [B, 1, N]
    x = grid_logits[:, None, :]  # [B, 1, N]
    above = (probs * (x > high)).sum(-1)
    tied = (probs * ((x > low) & (x <= high))).sum(-1)
    return hdr_levels(above, tied, u).masked_fill(~mask.to(grid_logits.device), math.nan)


def hdr_coverage_counts(hdr_level: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """For each image, how many of its real targets lie in the HDR of each mass of :data:`HDR_LEVELS`
    (``q < alpha``): ``(B, len(HDR_LEVELS))`` int64, from HDR levels ``(B, M)`` (NaN on padding)."""
    if hdr_level.ndim != 2:
        raise ConfigError(f"hdr_level must have shape (B, M), got {tuple(hdr_level.shape)}")
    real = ~torch.isnan(hdr_level) if mask is None else mask.to(hdr_level.device)
    alphas = torch.tensor(HDR_LEVELS, dtype=torch.float64, device=hdr_level.device)
    inside = (hdr_level.double()[..., None] < alphas) & real[..., None]  # [B, M, L]
    return inside.sum(dim=1)


@constant_cache(maxsize=4)
def _flat_grid(level: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    return so3_healpix_grid(level, dtype=dtype).reshape(-1, 9).to(device)  # [N, 9]


def spread_deg(
    dist: PoseDistribution,
    targets: torch.Tensor,
    mask: torch.Tensor | None,
    level: int,
    max_pairs: int = 2**24,
) -> torch.Tensor:
    """``sum_i p_i * min_j angle(R_i, R_gt_j)`` in degrees on the grid of ``level``: ``(B,)``.

    ``p_i`` is the grid softmax of any density method (:meth:`PoseDistribution.log_prob_grid`). The
    minimum over ground truths uses ``trace(R_i^T R_j) = <vec R_i, vec R_j>``: one matmul per block of
    at most ``max_pairs`` (grid point, target) pairs.
    """
    mask = check_targets(targets, mask, dist.batch_size)
    level = check_level(level)
    grid = _flat_grid(level, dist.dtype, str(dist.device))  # [N, 9]
    n = grid.shape[0]
    out = torch.empty(dist.batch_size, dtype=dist.dtype, device=dist.device)
    with torch.no_grad():
        probs = dist.log_prob_grid(level).exp()  # [B, N]
        for b in range(dist.batch_size):
            gt = targets[b][mask[b]].reshape(-1, 9).to(grid)  # [m, 9]
            block = max(1, max_pairs // len(gt))
            total = grid.new_zeros(())
            for i in range(0, n, block):
                trace = (grid[i : i + block] @ gt.T).amax(dim=1)  # [n_block]  max trace = min angle
                angle = torch.rad2deg(torch.acos(((trace - 1) / 2).clamp(-1.0, 1.0)))
                total += (probs[b, i : i + block] * angle).sum()
            out[b] = total
    return out


def _median(x: torch.Tensor) -> float:
    # torch.median returns the lower of the two middle values; use the usual mean of the two.
    return float(torch.quantile(x.double(), 0.5)) if len(x) else math.nan


def _mean_of_image_means(sums: torch.Tensor, counts: torch.Tensor, sel: torch.Tensor) -> float:
    """The mean over the selected images of ``sums / counts`` (each image's mean over its pairs)."""
    return float((sums.cpu()[sel].double() / counts.cpu()[sel].double()).mean())


def summarize_pose_metrics(
    class_index: torch.Tensor,
    class_names: Sequence[str],
    error_deg: torch.Tensor | None = None,
    ll_sum: torch.Tensor | None = None,
    ll_count: torch.Tensor | None = None,
    spread: torch.Tensor | None = None,
    ll_exact_sum: torch.Tensor | None = None,
    hdr_counts: torch.Tensor | None = None,
) -> dict[str, float]:
    """Per-class and class-averaged metrics from per-image records (all ``(n_images,)``, ``hdr_counts``
    ``(n_images, len(HDR_LEVELS))``).

    Keys: ``{metric}/{class}`` for each class present and ``{metric}`` for the mean over those
    classes, with metric in ``log_likelihood`` (the mean over the class's images of each image's mean
    over its equivalent set: per-image sums ``ll_sum`` over pair counts ``ll_count``), ``spread_deg``,
    ``acc15``, ``acc30``, ``median_error_deg``, ``log_likelihood_exact`` (the same mean of a family's
    continuous log density, from ``ll_exact_sum``, for families with a closed-form normaliser), and the
    calibration:
    ``hdr_coverage_10`` ... ``hdr_coverage_90`` (the fraction of the class's pairs inside the HDR of
    that mass, from per-image counts ``hdr_counts`` (:func:`hdr_coverage_counts`) over ``ll_count``)
    and ``calibration_ece`` (the mean over the levels of ``|coverage - alpha|``); plus ``n_images``.
    """
    class_index = class_index.long().cpu()
    present = [c for c in range(len(class_names)) if (class_index == c).any()]
    out: dict[str, float] = {"n_images": float(len(class_index))}
    per_metric: dict[str, list[float]] = {}

    def put(metric: str, c: int, value: float) -> None:
        out[f"{metric}/{class_names[c]}"] = value
        per_metric.setdefault(metric, []).append(value)

    for c in present:
        sel = class_index == c
        if ll_sum is not None and ll_count is not None:
            put("log_likelihood", c, _mean_of_image_means(ll_sum, ll_count, sel))
        if ll_exact_sum is not None and ll_count is not None:
            put("log_likelihood_exact", c, _mean_of_image_means(ll_exact_sum, ll_count, sel))
        if hdr_counts is not None and ll_count is not None:
            coverage = hdr_counts.cpu()[sel].double().sum(0) / ll_count.cpu()[sel].double().sum()  # [L]
            for key, value in zip(HDR_COVERAGE_KEYS, coverage.tolist(), strict=True):
                put(key, c, value)
            alphas = torch.tensor(HDR_LEVELS, dtype=torch.float64)
            put("calibration_ece", c, float((coverage - alphas).abs().mean()))
        if spread is not None:
            put("spread_deg", c, float(spread.cpu()[sel].double().mean()))
        if error_deg is not None:
            err = error_deg.cpu()[sel].double()
            for t in ACC_THRESHOLDS_DEG:
                put(f"acc{t:g}", c, float((err <= t).double().mean()))
            put("median_error_deg", c, _median(err))
    for metric, values in per_metric.items():
        out[metric] = float(sum(values) / len(values))
    return out
