"""Recalibration of a trained model by one temperature (docs/evaluation.md#recalibration).

Conventions
-----------
* The recalibrated distribution of an image is its predicted density raised to the power ``1 / T``
  and renormalised (:meth:`~image2sphere.distributions.base.PoseDistribution.tempered`), with one
  temperature ``T > 0`` for the whole run: ``T < 1`` sharpens every distribution, ``T > 1`` broadens
  it. The order of the rotations by density does not change, so neither do the mode, the point
  estimate's errors and accuracies, nor which rotations a region of given mass starts from; what
  changes is how much mass every region holds, i.e. the log likelihood, the spread and the calibration.
* ``T`` is fitted on the validation split: the value in ``[TEMPERATURE_BOUNDS]`` that maximises the
  validation log likelihood as the test's headline reads it: each image's mean over its equivalent
  rotations, read at the grid point nearest each rotation on the grid of ``grid_level``, the mean over
  a class's images, then the mean over classes (so an image with many equivalent rotations weighs as
  much as one with few, and a class with few images as much as any other). The log likelihood is a proper
  scoring rule: it is maximised by the temperature whose regions hold the mass they claim. The
  search is a bounded one-dimensional search on ``log T`` (scipy's ``minimize_scalar``) over the grid
  values of every validation image, computed once (at most ``MAX_FIT_BYTES``: a coarser grid is used for a
  split too large for the test's grid, :func:`fit_level`); ``T = 1`` is kept when nothing beats it.
* A fit that ends at a bound of the search (within ``2 xatol`` of it on ``log T``) is **degenerate**: at the
  upper bound the validation log likelihood keeps rising as every distribution is flattened towards the
  uniform one, i.e. the model's density carries no information on that split; at the lower bound it keeps
  rising as they are sharpened without limit (the validation rotations sit at the modes, e.g. a few images
  the model has memorised). Either way the value is an artefact of the bound, not a calibration: a warning
  says so, and the fit keeps ``T = 1`` (the model's own distribution), recording the bound it reached in
  ``degenerate_temperature``. The train and eval paths both go through :func:`fit_temperature`, so both
  store this ``T = 1`` record instead of the bound.
* The fit also reports the validation ECE before and after (the mean over classes, the tie-break
  uniforms drawn per image as the test draws them), and, as a diagnostic, the temperature each class
  alone would get (``class_temperatures``): far apart, they say that one temperature cannot calibrate
  every class.
* In a distributed run every process scores its own share of the validation split and the sums are
  added up across processes (``reduce``), so every process follows the same search and finds the
  same ``T``.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from typing import NamedTuple

import torch

from image2sphere.checks import ConfigError, check_int, check_number
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY, PoseDistribution, check_temperature
from image2sphere.metrics import HDR_LEVELS, density_pairs, hdr_coverage_counts
from image2sphere.rotation_sets import check_targets, fill_padding
from image2sphere.so3.grid import MAX_DENSE_LEVEL, check_level, so3_grid_size, so3_healpix_nearest_index

__all__ = [
    "TEMPERATURE_BOUNDS",
    "Recalibration",
    "degenerate_fit_message",
    "ScoredPairs",
    "fit_level",
    "fit_temperature",
    "score_temperature",
]

log = logging.getLogger(__name__)

#: the temperatures searched: from 50 times sharper to 50 times broader
TEMPERATURE_BOUNDS = (0.02, 50.0)
#: the most memory the fit's grid values may take (float64, every validation image at once)
MAX_FIT_BYTES = 2 * 2**30


class ScoredPairs(NamedTuple):
    """One validation batch: its distributions, targets ``(B, M, 3, 3)``, mask ``(B, M)``, the tie-break
    uniforms ``(B, M)`` of its HDR levels (:func:`~image2sphere.metrics.tie_break_uniforms`) and the
    images' classes ``(B,)``."""

    dist: PoseDistribution
    targets: torch.Tensor
    mask: torch.Tensor
    u: torch.Tensor
    class_index: torch.Tensor


@dataclass(frozen=True)
class Recalibration:
    """A fitted temperature and what it did on the split it was fitted on (stored in checkpoints as a
    plain dict, :meth:`to_dict`). ``degenerate_temperature``: where the search ended when it ended at a
    bound (the fit is degenerate, module docstring; ``temperature`` is then 1), else ``None``."""

    temperature: float
    grid_level: int
    split: str
    n_images: int
    n_pairs: int
    log_likelihood_before: float
    log_likelihood_after: float
    ece_before: float
    ece_after: float
    class_temperatures: tuple[float, ...] = ()
    degenerate_temperature: float | None = None

    @property
    def degenerate(self) -> bool:
        """Whether the search ended at a bound (``temperature`` is then 1: no recalibration)."""
        return self.degenerate_temperature is not None

    def to_dict(self) -> dict:
        return asdict(self)

    @classmethod
    def from_dict(cls, data: dict, source: str = "the checkpoint") -> Recalibration:
        """Back from :meth:`to_dict`; ``ValueError`` naming ``source`` when a field is missing or wrong."""
        if not isinstance(data, dict):
            raise ConfigError(f"the recalibration stored in {source} is not a dict: {type(data).__name__}")
        missing = sorted(set(cls.__dataclass_fields__) - set(data) - {"class_temperatures", "degenerate_temperature"})
        if missing:
            raise ConfigError(f"the recalibration stored in {source} lacks {', '.join(missing)}")
        fields = {k: data[k] for k in cls.__dataclass_fields__ if k in data}
        fields["class_temperatures"] = tuple(float(t) for t in fields.get("class_temperatures", ()))
        try:
            check_temperature(fields["temperature"], f"the temperature stored in {source}")
            if fields.get("degenerate_temperature") is not None:
                check_temperature(fields["degenerate_temperature"], f"the degenerate temperature stored in {source}")
            check_level(fields["grid_level"], name=f"the grid level stored in {source}")
        except ValueError as e:
            raise ConfigError(f"{e}; fit it again with recalibration=fit") from None
        return cls(**fields)

    def describe(self) -> str:
        """One line for the log."""
        where = f"the {self.split} split ({self.n_images} images, {self.n_pairs} pairs, grid level {self.grid_level})"
        if self.degenerate:
            head = (
                f"no temperature (T = 1 kept): the fit on {where} ended at the search bound, "
                f"T = {self.degenerate_temperature:.4g} (degenerate, see the warning): log likelihood "
                f"{self.log_likelihood_before:.3f}, ECE {self.ece_before:.3f}"
            )
        else:
            head = (
                f"temperature {self.temperature:.4g} fitted on {where}: log likelihood "
                f"{self.log_likelihood_before:.3f} -> {self.log_likelihood_after:.3f}, "
                f"ECE {self.ece_before:.3f} -> {self.ece_after:.3f}"
            )
        if len(self.class_temperatures) < 2:
            return head
        each = ", ".join(f"{t:.3g}" + (" (a bound)" if _at_bound(t) else "") for t in self.class_temperatures)
        return f"{head}; each class alone: {each}"

    def same_temperature(self, other: Recalibration | None, xatol: float = 0.01) -> bool:
        """Whether ``other`` holds the same recalibration up to the search's tolerance: both degenerate, or
        neither and their temperatures within ``2 xatol`` on ``log T`` (a refit of the same weights on the
        same split lands there)."""
        if other is None or self.degenerate != other.degenerate:
            return False
        return self.degenerate or abs(math.log(self.temperature / other.temperature)) <= 2 * xatol


def _at_bound(temperature: float, bounds: tuple[float, float] = TEMPERATURE_BOUNDS, xatol: float = 0.01) -> bool:
    """Whether ``temperature`` is within ``2 xatol`` of a bound on ``log T`` (where the bounded search ends
    when the log likelihood keeps rising towards that bound)."""
    return any(abs(math.log(temperature / b)) <= 2 * xatol for b in bounds)


def degenerate_fit_message(
    temperature: float, split: str = "val", bounds: tuple[float, float] = TEMPERATURE_BOUNDS
) -> str:
    """The warning for a fit that ended at a bound (module docstring): what the bound means, and what is kept."""
    low, high = bounds
    if abs(math.log(temperature / high)) < abs(math.log(temperature / low)):
        meaning = (
            f"at the upper bound {high:g}: the {split} log likelihood keeps rising as every distribution is "
            f"flattened towards uniform, i.e. the model's density carries no information on the {split} split "
            "(a model that has not learned, or too few validation images)"
        )
    else:
        meaning = (
            f"at the lower bound {low:g}: the {split} log likelihood keeps rising as every distribution is "
            f"sharpened without limit, i.e. the {split} rotations sit at the modes (too few validation images, "
            "or images the model has memorised)"
        )
    return (
        f"Recalibration is degenerate: the fitted temperature {temperature:.4g} is {meaning}. It is not used: "
        "T = 1 is kept (the model's own distribution) and stored as such"
    )


def _class_means(sums: torch.Tensor, counts: torch.Tensor) -> torch.Tensor:
    """``sums (C, ...) / counts (C,)`` for the classes with pairs: ``(C', ...)``."""
    present = counts > 0
    return sums[present] / counts[present].reshape(-1, *([1] * (sums.ndim - 1)))


def score_temperature(
    batches: Iterable[ScoredPairs],
    temperature: float,
    level: int,
    num_classes: int,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
) -> tuple[float, float, int]:
    """``(log likelihood, ECE, number of pairs)`` of the batches' distributions at ``temperature`` on the
    grid of ``level`` (one streamed sweep per batch, :func:`~image2sphere.metrics.density_pairs`, as the
    test scores them), each the mean over the classes of the class's value: for the log likelihood the
    mean over its images of each image's mean over its real pairs, for the ECE the coverage over its real
    pairs. ``reduce`` sums a float64 tensor across processes (identity when ``None``)."""
    temperature = check_temperature(temperature)
    n_levels = len(HDR_LEVELS)
    # [C, (sum of image means, images, pairs, HDR counts)]
    totals = torch.zeros(num_classes, 3 + n_levels, dtype=torch.float64)
    for batch in batches:
        dist = batch.dist.tempered(temperature)
        pairs = density_pairs(dist, batch.targets, batch.mask, level, batch.u)
        mask = batch.mask.to(pairs.log_density.device)
        n_pairs = mask.sum(1, keepdim=True).double()  # [B, 1]
        rows = torch.cat(
            [
                pairs.log_density.double().masked_fill(~mask, 0.0).sum(1, keepdim=True) / n_pairs,
                torch.ones_like(n_pairs),
                n_pairs,
                hdr_coverage_counts(pairs.hdr_level, mask).double(),
            ],
            dim=1,
        ).cpu()  # [B, 3 + L]
        totals.index_add_(0, batch.class_index.long().cpu(), rows)
    if reduce is not None:
        totals = reduce(totals).double().cpu()
    n = int(totals[:, 2].sum())
    if n == 0:
        raise ConfigError("no validation pair to fit a temperature on: the validation split is empty")
    log_likelihood = _class_means(totals[:, :1], totals[:, 1])[:, 0]  # [C']
    coverage = _class_means(totals[:, 3:], totals[:, 2])  # [C', L]
    alphas = torch.tensor(HDR_LEVELS, dtype=torch.float64)
    ece = (coverage - alphas).abs().mean(1)  # [C']
    return float(log_likelihood.mean()), float(ece.mean()), n


class _GridValues(NamedTuple):
    """One batch's unnormalised log density on the whole grid ``(B, N)``, the sum of its values at each
    image's real pairs' nearest grid points ``(B,)``, the number of real pairs per image ``(B,)`` and the
    images' classes ``(B,)``."""

    grid: torch.Tensor
    at_pairs: torch.Tensor
    pairs: torch.Tensor
    class_index: torch.Tensor


def _grid_values(batch: ScoredPairs, level: int) -> _GridValues:
    mask = check_targets(batch.targets, batch.mask, batch.dist.batch_size)
    grid = batch.dist.grid_log_density(level).double()  # [B, N]
    index = so3_healpix_nearest_index(fill_padding(batch.targets, mask), level).to(grid.device)  # [B, M]
    mask = mask.to(grid.device)
    at_pairs = grid.gather(1, index).masked_fill(~mask, 0.0).sum(1)
    return _GridValues(grid, at_pairs, mask.sum(1).double(), batch.class_index.long().to(grid.device))


def fit_level(level: int, n_images: int) -> int:
    """The grid the fit reads: ``level``, or the finest coarser one whose values for ``n_images`` images fit
    in :data:`MAX_FIT_BYTES` (the values are kept for the whole search)."""
    level = check_level(level, name="the recalibration grid level", max_level=MAX_DENSE_LEVEL)
    while level > 0 and n_images * math.prod(so3_grid_size(level)) * 8 > MAX_FIT_BYTES:
        level -= 1
    return level


def fit_temperature(
    batches: list[ScoredPairs],
    level: int,
    num_classes: int | None = None,
    split: str = "val",
    n_images: int | None = None,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
    bounds: tuple[float, float] = TEMPERATURE_BOUNDS,
    xatol: float = 0.01,
) -> Recalibration:
    """The temperature that maximises the batches' log likelihood, the mean over classes of each class's
    mean over its images of each image's mean over its pairs, on the grid of ``level`` (module docstring;
    :func:`fit_level` picks a coarser grid where the values would not fit in memory). ``num_classes``: the
    number of classes (default: the largest class index + 1; give it in a distributed run, where a process
    may not see every class).

    Each distribution's values on the grid are computed once; the search then only rescales them (the
    log likelihood of a pair at temperature ``T`` is ``v / T - logsumexp(grid / T) + log N - log(pi^2)``).
    ``xatol``: the search's tolerance on ``log T`` (0.01: T to within 1 %). The ECE before and after is
    then scored by two streamed sweeps (:func:`score_temperature`). A search that ends at a bound is
    degenerate (module docstring): a warning, and ``T = 1`` with ``degenerate_temperature`` set.
    """
    from scipy.optimize import minimize_scalar

    images = n_images if n_images is not None else sum(len(b.targets) for b in batches)
    level = fit_level(level, images)
    low, high = (check_temperature(b, "a temperature bound") for b in bounds)
    if not low < 1.0 < high:
        raise ConfigError(f"the temperature bounds must enclose 1, got {bounds}")
    check_number("xatol", xatol)
    if num_classes is None:
        num_classes = 1 + max((int(b.class_index.max()) for b in batches if len(b.class_index)), default=0)
    check_int("num_classes", num_classes, 1)
    values = [_grid_values(b, level) for b in batches]
    constant = math.log(math.prod(so3_grid_size(level))) + LOG_UNIFORM_DENSITY

    def class_log_likelihoods(temperature: float) -> tuple[torch.Tensor, torch.Tensor]:
        """Per class: the sum over its images of each image's mean log likelihood over its pairs, and its
        number of images ``(C,)`` each."""
        totals = torch.zeros(num_classes, 2, dtype=torch.float64)
        for v in values:
            lse = torch.logsumexp(v.grid / temperature, dim=1)  # [B]
            image_mean = v.at_pairs / (temperature * v.pairs) - lse + constant  # [B]
            rows = torch.stack([image_mean, torch.ones_like(image_mean)], dim=1)
            totals.index_add_(0, v.class_index.cpu(), rows.cpu())
        if reduce is not None:
            totals = reduce(totals).double().cpu()
        return totals[:, 0], totals[:, 1]

    def search(objective: Callable[[float], float]) -> float:
        result = minimize_scalar(
            lambda x: -objective(math.exp(x)),
            bounds=(math.log(low), math.log(high)),
            method="bounded",
            options={"xatol": xatol},
        )
        temperature = float(math.exp(result.x))
        return temperature if objective(temperature) > objective(1.0) else 1.0  # nothing beats T = 1

    def headline(temperature: float) -> float:
        sums, counts = class_log_likelihoods(temperature)
        if counts.sum() == 0:
            raise ConfigError("no validation pair to fit a temperature on: the validation split is empty")
        return float(_class_means(sums, counts).mean())

    temperature = search(headline)
    degenerate = None
    if temperature != 1.0 and _at_bound(temperature, (low, high), xatol):
        log.warning(degenerate_fit_message(temperature, split, (low, high)))
        degenerate, temperature = temperature, 1.0
    _, counts = class_log_likelihoods(1.0)
    present = [c for c in range(num_classes) if counts[c] > 0]
    per_class = tuple(search(lambda t, c=c: float(class_log_likelihoods(t)[0][c] / counts[c])) for c in present)
    values.clear()  # the grid values are not needed any more
    before = score_temperature(batches, 1.0, level, num_classes, reduce)
    after = score_temperature(batches, temperature, level, num_classes, reduce) if temperature != 1.0 else before
    return Recalibration(
        temperature=temperature,
        grid_level=level,
        split=split,
        n_images=check_int("n_images", images),
        n_pairs=before[2],
        log_likelihood_before=before[0],
        log_likelihood_after=after[0],
        ece_before=before[1],
        ece_after=after[1],
        class_temperatures=per_class if len(per_class) > 1 else (),
        degenerate_temperature=degenerate,
    )
