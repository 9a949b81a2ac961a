"""Pose metrics (docs/evaluation.md), per image and summarised per class.

Conventions
-----------
* Ground truth is a padded set of equivalent rotations per image: ``targets (B, M, 3, 3)`` with a
  boolean ``mask (B, M)`` marking the real entries (a symmetric object has several rotations that
  give the same image; an asymmetric one has ``M = 1``). ``targets[:, 0]`` is always real.
* Angular error of a point estimate: the geodesic angle to the nearest equivalent rotation, in
  degrees. Acc@t is the fraction of images with error <= t degrees.
* Log likelihood: the model's log density (Haar measure of volume pi^2, read at the grid point
  nearest the rotation, :meth:`SO3Distribution.log_density`) at EVERY real (image, equivalent
  rotation) pair; a class's value is the mean over all its pairs. Uniform gives -log(pi^2) = -2.29.
* Spread: ``sum_i p_i * min_j angle(R_i, R_gt_j)`` in degrees over the grid of a level, with ``p``
  the grid softmax: how far (on average) the probability mass lies from the nearest ground truth.
* Headline numbers are means over classes of the per-class values.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from functools import lru_cache

import torch

from image2sphere.distributions.base import LOG_UNIFORM_DENSITY, PoseDistribution
from image2sphere.so3.grid import check_level, so3_grid_size, so3_healpix_grid, so3_healpix_nearest_index
from image2sphere.so3.rotations import geodesic_distance_deg

__all__ = [
    "ACC_THRESHOLDS_DEG",
    "check_targets",
    "log_density_from_grid_logits",
    "log_likelihood_pairs",
    "min_angular_error_deg",
    "spread_deg",
    "summarize_pose_metrics",
]

ACC_THRESHOLDS_DEG = (15.0, 30.0)


def check_targets(targets: torch.Tensor, mask: torch.Tensor | None, batch: int | None = None) -> torch.Tensor:
    """Validate ``targets (B, M, 3, 3)`` and return the mask ``(B, M)`` (all real when ``None``)."""
    if targets.ndim != 4 or targets.shape[-2:] != (3, 3) or targets.shape[1] < 1:
        raise ValueError(f"targets must have shape (B, M, 3, 3) with M >= 1, got {tuple(targets.shape)}")
    if batch is not None and targets.shape[0] != batch:
        raise ValueError(f"targets must have batch size {batch}, got {tuple(targets.shape)}")
    if mask is None:
        return torch.ones(targets.shape[:2], dtype=torch.bool, device=targets.device)
    if mask.shape != targets.shape[:2] or mask.dtype != torch.bool:
        raise ValueError(f"mask must be bool of shape {tuple(targets.shape[:2])}, got {tuple(mask.shape)} {mask.dtype}")
    if not mask[:, 0].all():
        raise ValueError("mask[:, 0] must be True: the first target of every image is its rendering rotation")
    return mask


def fill_padding(targets: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Padding entries (possibly NaN) replaced by the image's first target, so they can be read safely."""
    return torch.where(mask[..., None, None], targets, targets[:, :1].expand_as(targets))


def min_angular_error_deg(pred: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None = None) -> torch.Tensor:
    """Angle ``(B,)`` in degrees from ``pred (B, 3, 3)`` to the nearest real target."""
    if pred.ndim != 3 or pred.shape[-2:] != (3, 3):
        raise ValueError(f"pred must have shape (B, 3, 3), got {tuple(pred.shape)}")
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


def log_density_from_grid_logits(
    grid_logits: torch.Tensor, targets: torch.Tensor, mask: torch.Tensor | None, level: int
) -> torch.Tensor:
    """Log density ``(B, M)`` (NaN where masked) from dense logits ``(B, N)`` on the grid of ``level``.

    ``log_softmax(logits)[nearest(R)] + log(N / pi^2)``: the dense reference of the streamed path
    (:meth:`SO3Distribution.log_density`), usable with any hand-made or externally computed logits.
    """
    level = check_level(level)
    n_points = math.prod(so3_grid_size(level))
    if grid_logits.ndim != 2 or grid_logits.shape[1] != n_points:
        raise ValueError(
            f"grid_logits must have shape (B, {n_points}) for level {level}, got {tuple(grid_logits.shape)}"
        )
    mask = check_targets(targets, mask, len(grid_logits))
    index = so3_healpix_nearest_index(fill_padding(targets, mask), level).to(grid_logits.device)  # [B, M]
    log_p = torch.log_softmax(grid_logits, dim=1).gather(1, index)  # [B, M]
    return (log_p + math.log(n_points) + LOG_UNIFORM_DENSITY).masked_fill(~mask, math.nan)


@lru_cache(maxsize=4)
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


def summarize_pose_metrics(
    class_index: torch.Tensor,
    class_names: Sequence[str],
    error_deg: torch.Tensor | None = None,
    ll_sum: torch.Tensor | None = None,
    ll_count: torch.Tensor | None = None,
    spread: torch.Tensor | None = None,
    ll_exact_sum: torch.Tensor | None = None,
) -> dict[str, float]:
    """Per-class and class-averaged metrics from per-image records (all ``(n_images,)``).

    Keys: ``{metric}/{class}`` for each class present and ``{metric}`` for the mean over those
    classes, with metric in ``log_likelihood`` (mean over all pairs of the class, from per-image
    sums ``ll_sum`` and pair counts ``ll_count``), ``spread_deg``, ``acc15``, ``acc30``,
    ``median_error_deg``, and ``log_likelihood_exact`` (the same mean of a family's continuous log
    density, from ``ll_exact_sum``, for families with a closed-form normaliser); plus ``n_images``.
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
            put("log_likelihood", c, float(ll_sum.cpu()[sel].double().sum() / ll_count.cpu()[sel].double().sum()))
        if ll_exact_sum is not None and ll_count is not None:
            count = ll_count.cpu()[sel].double().sum()
            put("log_likelihood_exact", c, float(ll_exact_sum.cpu()[sel].double().sum() / count))
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
