"""The one interface every pose method's output goes through: a batch of distributions over SO(3).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``.
* Densities are w.r.t. the Haar measure normalised to total volume ``pi^2``: a uniform distribution
  has log density ``-log(pi^2)`` (:data:`LOG_UNIFORM_DENSITY`).
* **The grid protocol.** Every density method is scored like I2S: its (unnormalised) log density is
  evaluated on the HEALPix SO(3) grid of a level and put through a softmax, ``p_i``; the density at
  ``R`` is ``p_nearest(R) * N / pi^2`` and the point estimate is the grid argmax. The grid is
  swept in chunks of rotations (never a ``(B, N)`` tensor unless asked for one). A family with a
  closed-form normaliser also gives its continuous density (:meth:`PoseDistribution.exact_log_density`).

* **Highest-density-region masses** (:meth:`PoseDistribution.grid_summary`, docs/evaluation.md#calibration):
  for a query rotation with nearest grid point ``t``, the grid mass strictly above it,
  ``sum_{i: p_i > p_t} p_i``, and the mass tied with it, ``sum_{i: p_i == p_t} p_i`` (``t`` itself
  included). "Tied" means equal up to a relative tolerance in log space (:func:`tie_tolerance`), so
  that values equal in exact arithmetic but computed by two code paths still tie. They come out of
  the same streamed sweep as the log normaliser, the maximum and the argmax.

A family subclasses :class:`PoseDistribution` and implements :meth:`~PoseDistribution.unnormalized_log_density`
(and, where the family has them, :meth:`~PoseDistribution.exact_log_normalizer`,
:meth:`~PoseDistribution.exact_mode` and :meth:`~PoseDistribution.exact_sample`). Everything else
(grid reductions, nearest-point log density, modes, sampling on the grid, points above a threshold)
comes from this class. A point regressor subclasses :class:`PointEstimate` instead: it has a mode
and no density.

* **Mixed precision** (:mod:`image2sphere.precision`): every method of this class and of each family
  (``__init__``, class methods and property getters included) computes in float32 (or float64 where
  the family's parameters are) under an enclosing ``torch.autocast``: :meth:`PoseDistribution.__init_subclass__`
  wraps them, when a family is defined, in :func:`~image2sphere.precision.float32_region` (autocast
  off, float16/bfloat16 tensor arguments cast to float32). Log densities, grid sweeps, logsumexps,
  normalisers, modes and samples are never evaluated in reduced precision, whoever calls them; the
  grid tables cached for later calls are built the same way. Without autocast nothing changes.
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import NamedTuple

import torch

from image2sphere.checks import check_int
from image2sphere.precision import constant_cache, float32_methods
from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    check_level,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)
from image2sphere.so3.grid_eval import MAX_OUTPUT_BYTES, check_streamed_level, exp_floor
from image2sphere.so3.rotations import check_rotation_matrix

__all__ = [
    "LOG_UNIFORM_DENSITY",
    "DensityNotAvailable",
    "GridSummary",
    "HdrMassAccumulator",
    "PointEstimate",
    "PoseDistribution",
    "check_threshold",
    "tie_tolerance",
]

LOG_UNIFORM_DENSITY = -math.log(math.pi**2)  # -2.2894
# grid rotations per chunk of the generic sweep: B x CHUNK values at a time
CHUNK_POINTS = 1 << 16


@constant_cache(maxsize=2)
def _grid_rotations(level: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    """The rotations of the grid of ``level`` ``(N, 3, 3)``, pixel-major (85 MB at level 5 in float32)."""
    return so3_healpix_grid(level, dtype=dtype).to(device)


class DensityNotAvailable(NotImplementedError):
    """The method predicts a rotation, not a distribution: it has no density (log likelihood, spread)."""


def check_threshold(threshold, name: str = "threshold") -> torch.Tensor:
    """A probability threshold (a number, or a tensor of them) as a float64 tensor; ``ValueError``
    unless every value is a probability in ``(0, 1]``."""
    message = f"{name} must be > 0 and <= 1 (a probability in (0, 1]), got {{!r}}"
    if isinstance(threshold, (bool, str)) or threshold is None:
        raise ValueError(message.format(threshold))
    try:
        values = torch.as_tensor(threshold, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ValueError(message.format(threshold)) from None
    if not ((values > 0) & (values <= 1)).all():  # NaN fails both comparisons
        raise ValueError(message.format(threshold if values.numel() == 1 else values.tolist()))
    return values


def tie_tolerance(values: torch.Tensor) -> torch.Tensor:
    """Half-width of the band of log densities that count as tied with ``values`` (any shape, same shape
    out): ``128 * eps(dtype) * max(1, |value|)`` (1.5e-5 relative in float32, 2.8e-14 in float64).

    Two grid values that are equal in exact arithmetic (a uniform or piecewise-constant density) can
    differ in the last bits when one is computed on a grid chunk and the other at a single query; the
    band makes them tie. For a smooth density it holds a negligible mass besides the query's own point.
    """
    eps = torch.finfo(values.dtype).eps
    return 128 * eps * values.abs().clamp_min(1.0)


class GridSummary(NamedTuple):
    """What one streamed sweep of the grid of a level gives (:meth:`PoseDistribution.grid_summary`).

    ``log_normalizer``, ``max`` ``(B,)``: logsumexp and maximum of the unnormalised log density over the
    grid; ``argmax`` ``(B,)``: pixel-major index of the maximum. For query rotations ``(B, K, 3, 3)``
    (else ``None``): ``index`` ``(B, K)``, the nearest grid point ``t`` of each; ``log_prob`` ``(B, K)``,
    ``log p_t``; ``mass_above`` and ``mass_tied`` ``(B, K)`` float64, ``sum_{p_i > p_t} p_i`` and
    ``sum_{p_i == p_t} p_i`` (ties up to :func:`tie_tolerance`; ``t`` itself is tied, so ``mass_tied >= p_t``).
    """

    log_normalizer: torch.Tensor
    max: torch.Tensor
    argmax: torch.Tensor
    index: torch.Tensor | None = None
    log_prob: torch.Tensor | None = None
    mass_above: torch.Tensor | None = None
    mass_tied: torch.Tensor | None = None


class HdrMassAccumulator:
    """Streams chunks of grid values into, for each of ``K`` query values per distribution, the grid
    mass above the query and the mass tied with it (see :class:`GridSummary`), without a
    ``(B, K, chunk)`` comparison.

    Args:
        query_values: ``(B, K)``, the unnormalised log density at each query's grid point, as read at the
            query (:meth:`PoseDistribution._values_at_index`).
        query_index: ``(B, K)``, the pixel-major index of each query's grid point. The sweep's own value
            there is picked up on the way, and the point itself is always counted as tied, even when
            the two computations of its value differ by more than the tie tolerance.
        n_gamma: the grid's gammas per pixel: :meth:`add` then groups chunks of whole fibres as
            :meth:`add_fibres` does.

    Method: the ``E = 2K`` band edges ``v - tol`` and ``v + tol`` of each distribution are sorted once. A
    grid value ``x`` falls in bucket ``j`` = the number of edges ``< x``; the masses ``exp(x)`` are summed
    per bucket (``(B, E + 1)`` masses in float64, scaled by the largest value so far). At the end the
    mass strictly above the edge at sorted position ``s`` is the sum of the buckets ``> s`` (a suffix
    sum): ``mass_above`` is that of ``v + tol`` and ``mass_tied`` that of ``v - tol`` minus it, the mass
    of ``v - tol < x <= v + tol``.

    * Values come in small groups of neighbouring grid points (:meth:`add`, :meth:`add_fibres`). A group
      whose minimum and maximum fall in the same bucket (no edge between them: nearly all groups, since
      edges are few and groups small) adds its mass in one piece; only the values of the other groups
      are bucketed one by one. Groups more than :attr:`NEGLIGIBLE` below the best lower bound known of
      the grid's logsumexp (a query's value, a chunk's maximum, the sweep's own bound) are skipped:
      together they weigh less than ``1e-14`` of the grid's mass.
    * Bucketing: up to :attr:`COMPARE_EDGES` edges by comparisons; more through a table of
      :attr:`CELLS_PER_EDGE` ``* E`` equal cells of ``[min edge, max edge]`` per distribution. A value's
      cell is ``floor((x - min edge) * scale)``, computed the same way for edges and values, so it is
      monotone: in a cell that holds no edge the bucket is the number of edges in lower cells (exact,
      no search); only values in a cell that holds edges are placed among them, by a bisection of all
      such values at once.
    """

    #: consecutive pixels per group, at one gamma, on the Fourier fast path (:meth:`add_fibres`)
    GROUP_PIXELS = 8
    #: consecutive grid points per group in :meth:`add` when a chunk is not made of whole fibres
    GROUP_POINTS = 16
    #: at most this many edges are counted by comparisons, more through the cell table
    COMPARE_EDGES = 8
    #: cells of the table per edge
    CELLS_PER_EDGE = 16
    #: when more than this fraction of a chunk's groups lie among the edges, every value is bucketed
    DENSE_FRACTION = 0.25
    #: groups more than this far (in log density) below the highest value known are skipped
    NEGLIGIBLE = 50.0

    def __init__(self, query_values: torch.Tensor, query_index: torch.Tensor, n_gamma: int | None = None):
        if query_values.ndim != 2 or query_index.shape != query_values.shape:
            raise ValueError(
                f"query_values and query_index must have one shape (B, K), got {tuple(query_values.shape)} "
                f"and {tuple(query_index.shape)}"
            )
        self.batch_size, k = query_values.shape
        values = query_values.detach()
        self.query_values, self.query_index = values, query_index.to(values.device)
        self.n_gamma = n_gamma
        self.own_value = torch.full_like(values, math.nan)  # [B, K]: the sweep's value at each query's point
        # values below this are negligible: the grid's logsumexp is at least any query's value or any
        # chunk's maximum, and a point NEGLIGIBLE below it weighs e^-50 = 2e-22 (all of level 6: 4e-15)
        finite = torch.where(torch.isfinite(values), values, -math.inf)
        self._floor = torch.cat([finite, finite.new_full((self.batch_size, 1), -math.inf)], dim=1).amax(1, keepdim=True)
        self._floor -= self.NEGLIGIBLE
        tol = torch.where(torch.isfinite(values), tie_tolerance(values), torch.zeros_like(values))
        edges = torch.cat([values - tol, values + tol], dim=1)  # [B, E]: lower edges, then upper edges
        self.edges, order = edges.sort(dim=1)
        rank = torch.empty_like(order)
        rank.scatter_(1, order, torch.arange(2 * k, device=order.device).expand_as(order).contiguous())
        self.position_low, self.position_high = rank[:, :k], rank[:, k:]  # [B, K] each: sorted positions
        self.n_buckets = 2 * k + 1
        # bucket masses, float64, relative to exp(self._scale_of_mass) (the largest chunk maximum so far)
        self._mass = torch.zeros(self.batch_size, self.n_buckets, dtype=torch.float64, device=values.device)
        self._scale_of_mass = torch.full((self.batch_size, 1), -math.inf, dtype=torch.float64, device=values.device)
        self._table = None
        span = self.edges[:, -1:] - self.edges[:, :1]  # [B, 1]
        if 2 * k > self.COMPARE_EDGES and bool(torch.isfinite(span).all() and (span > 0).all()):
            self._cells = self.CELLS_PER_EDGE * 2 * k
            self._origin, self._scale = self.edges[:, :1], self._cells / span  # [B, 1] each
            cell = self._cell(self.edges, self._origin, self._scale).long()  # [B, E] in 0 .. cells + 1
            count = torch.zeros(self.batch_size, self._cells + 2, dtype=torch.long, device=values.device)
            count.scatter_add_(1, cell, torch.ones_like(cell))
            below = count.cumsum(1) - count  # edges in lower cells
            # per cell: its bucket when it holds no edge, else -1 - (the sorted position of its first edge);
            # and the number of edges in it
            self._table = torch.where(count > 0, -1 - below, below).view(-1), count.view(-1)

    def _cell(self, x: torch.Tensor, origin: torch.Tensor, scale: torch.Tensor) -> torch.Tensor:
        """Cell ``0 .. cells + 1`` of values ``x (R, n)`` (0 and the last: below and above every edge):
        ``floor((x - origin) * scale) + 1`` clamped, as int32. Each step is one correctly rounded
        operation, so the map is monotone and the same for edges and values."""
        return (x - origin).mul_(scale).clamp_(-1, self._cells).add_(1).int()

    def _bucket_rows(self, b: torch.Tensor, x: torch.Tensor) -> torch.Tensor:
        """The bucket (number of edges ``<``) of values ``x (S, n)``, row ``i`` of distribution ``b[i]``:
        ``(S, n)`` int64."""
        if self.edges.shape[1] <= self.COMPARE_EDGES:
            edges = self.edges[b]  # [S, E]
            bucket = torch.zeros(x.shape, dtype=torch.long, device=x.device)
            for j in range(edges.shape[1]):
                bucket += x > edges[:, j : j + 1]
            return bucket
        if self._table is None:  # no usable table: bisect over all the edges
            owner = b[:, None].expand_as(x).reshape(-1)
            zero = torch.zeros_like(owner)
            return self._bisect(owner, x.reshape(-1), zero, zero + self.edges.shape[1]).view(x.shape)
        code, count = self._table
        cell = self._cell(x, self._origin[b], self._scale[b]) + (b.int() * (self._cells + 2))[:, None]  # [S, n]
        cell = cell.view(-1)
        bucket = code.index_select(0, cell)  # [S * n]: the bucket, or -1 - (its first edge) in a cell with edges
        row, col = torch.nonzero((bucket < 0).view(x.shape), as_tuple=True)  # values in a cell that holds edges
        if len(row):
            inside = row * x.shape[1] + col
            first = -1 - bucket.index_select(0, inside)
            n_edges = count.index_select(0, cell.index_select(0, inside))
            value = x.reshape(-1).index_select(0, inside)
            bucket.index_copy_(0, inside, self._bisect(b.index_select(0, row), value, first, first + n_edges))
        return bucket.view(x.shape)

    def _bisect(self, owner: torch.Tensor, value: torch.Tensor, low: torch.Tensor, high: torch.Tensor) -> torch.Tensor:
        """For each value ``(D,)`` of distribution ``owner``, the number of its edges ``< value``, knowing that
        it lies in ``[low, high]`` (sorted positions): a branch-free binary search of all values at once,
        ``log2`` of the widest range in steps. Positions past ``high`` need no guard: their edges are
        ``>= value`` (or the ``+inf`` that pads each distribution's edges)."""
        n = self.edges.shape[1] + 1
        edges = torch.cat([self.edges, self.edges.new_full((self.batch_size, 1), math.inf)], dim=1).view(-1)
        base = owner * n
        position, last = base + low, base + (n - 1)  # flat position of the count so far; of the padding
        widest = int((high - low).max()) if len(value) else 0
        step = 1 << max(0, widest.bit_length() - 1)  # the largest power of two <= widest
        while widest and step:
            candidate = position + step
            below = edges.index_select(0, torch.minimum(candidate - 1, last)) < value
            position = torch.where(below, candidate, position)
            step >>= 1
        return position - base

    def _pick_own(self, values: torch.Tensor, start: int) -> None:
        """Record the values ``(B, n)`` of the chunk of grid points ``start .. start + n - 1`` at the queries."""
        local = self.query_index - start  # [B, K]
        inside = (local >= 0) & (local < values.shape[1])
        if inside.any():
            b, k = torch.nonzero(inside, as_tuple=True)
            self.own_value[b, k] = values[b, local[b, k]]

    def add(
        self,
        values: torch.Tensor,
        start: int,
        weights: torch.Tensor | None = None,
        reference: torch.Tensor | None = None,
    ) -> None:
        """One chunk of grid values ``(B, n)``: grid points ``start .. start + n - 1`` (pixel-major); every
        grid point must come exactly once over the sweep. ``weights = exp(values - reference)`` and
        ``reference (B,)`` when the caller has them (:func:`relative_exp`)."""
        values = values.detach().reshape(self.batch_size, -1)
        n = values.shape[1]
        if n == 0:
            return
        if weights is None or reference is None:
            weights, reference = relative_exp(values)
        G = self.n_gamma
        if G and start % G == 0 and n % G == 0:  # whole fibres: groups of pixels at one gamma
            shape = (self.batch_size, n // G, G)
            self.add_fibres(values.view(shape), weights.view(shape), reference, start // G)
            return
        self._pick_own(values, start)
        cut = n - n % self.GROUP_POINTS
        for sl, g in ((slice(0, cut), self.GROUP_POINTS), (slice(cut, n), n - cut)):
            if g and sl.stop > sl.start:
                view = (self.batch_size, -1, g, 1)  # groups along dim 2
                self._add_groups(values[:, sl].reshape(view), weights[:, sl].reshape(view), reference)

    def add_fibres(
        self,
        values: torch.Tensor,
        weights: torch.Tensor,
        reference: torch.Tensor,
        first_pixel: int,
        floor: torch.Tensor | None = None,
    ) -> None:
        """A chunk of whole gamma fibres ``values (B, P, G)`` of pixels ``first_pixel .. first_pixel + P - 1``
        with ``weights = exp(values - reference)``, ``reference (B,)`` (the Fourier fast path's pass
        computes both) and optionally a lower bound ``floor (B,)`` of the grid's logsumexp: groups of
        :attr:`GROUP_PIXELS` consecutive pixels at one gamma."""
        B, P, G = values.shape
        if floor is not None:
            self._floor = torch.maximum(self._floor, floor.reshape(B, 1).to(self._floor.dtype) - self.NEGLIGIBLE)
        self._pick_own(values.reshape(B, -1), first_pixel * G)
        cut = P - P % self.GROUP_PIXELS
        for sl, g in ((slice(0, cut), self.GROUP_PIXELS), (slice(cut, P), P - cut)):
            if g and sl.stop > sl.start:
                view = (B, -1, g, G)  # groups along dim 2 (pixels)
                self._add_groups(values[:, sl].reshape(view), weights[:, sl].reshape(view), reference)

    def _add_groups(self, values: torch.Tensor, weights: torch.Tensor, reference: torch.Tensor) -> None:
        """Grid values ``(B, Q, g, W)`` in groups along dim 2 (group ``(b, q, w)`` is ``values[b, q, :, w]``),
        ``weights = exp(values - reference)`` of the same shape, ``reference (B,)``. Every grid point
        must come exactly once over the sweep."""
        B, _, g, W = values.shape
        reference = reference.reshape(B, 1)
        self._floor = torch.maximum(self._floor, reference.to(self._floor.dtype) - self.NEGLIGIBLE)
        reference = reference.double()  # -inf: the chunk is all -inf and weighs nothing
        group_max = values.amax(dim=2).reshape(B, -1)  # [B, R]: R = Q * W groups
        group_min = values.amin(dim=2).reshape(B, -1)
        group_mass = weights.sum(dim=2).reshape(B, -1)
        # groups wholly below every edge (bucket 0: nothing to add), negligible, or wholly above every edge
        # (the last bucket) take two comparisons; only the others (among the edges) need their buckets
        below = group_max <= torch.maximum(self.edges[:, :1], self._floor)
        above = (group_min > self.edges[:, -1:]) & ~below
        among = torch.nonzero(~(below | above))  # [S, 2]: (distribution, group)
        sums = torch.zeros_like(self._mass)  # [B, E + 1], relative to the reference
        if len(among) > self.DENSE_FRACTION * below.numel():  # edges everywhere: bucket every value
            bucket = self._bucket_rows(torch.arange(B, device=values.device), values.reshape(B, -1))
            sums.scatter_add_(1, bucket, weights.reshape(B, -1).double())
        else:
            sums[:, -1] = torch.where(above, group_mass, 0.0).sum(dim=1, dtype=torch.float64)
            if len(among):
                b, r = among.unbind(1)
                top, bottom = self._bucket_rows(b, torch.stack([group_max[b, r], group_min[b, r]], dim=1)).unbind(1)
                whole = top == bottom  # no edge inside the group: its mass in one piece
                sums.index_put_((b[whole], top[whole]), group_mass[b[whole], r[whole]].double(), accumulate=True)
                b, r = b[~whole], r[~whole]  # the groups an edge cuts: their values one by one
                if len(b):
                    q, w = r // W, r % W
                    x, weight = values[b, q, :, w], weights[b, q, :, w]  # [S, g]
                    bucket = self._bucket_rows(b, x) + (b * self.n_buckets)[:, None]  # [S, g], flat
                    sums.view(-1).scatter_add_(0, bucket.reshape(-1), weight.double().reshape(-1))
        scale = torch.maximum(self._scale_of_mass, reference)  # [B, 1]
        # (-inf) - (-inf) is NaN: before the first chunk, or for a chunk of -inf; both weigh nothing
        old, new = (torch.exp(r - scale).nan_to_num(0.0) for r in (self._scale_of_mass, reference))
        self._mass = self._mass * old + sums * new
        self._scale_of_mass = scale

    def masses(self, log_normalizer: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mass_above, mass_tied)`` ``(B, K)`` float64, for the grid's logsumexp ``log_normalizer (B,)``."""
        log_normalizer = log_normalizer.detach().double()[:, None]
        mass = self._mass * torch.exp(self._scale_of_mass - log_normalizer).nan_to_num(0.0)  # [B, E + 1]
        above_edge = mass.flip(1).cumsum(1).flip(1)  # [B, E + 1]: [:, s + 1] is the mass above edge s
        above = above_edge.gather(1, self.position_high + 1)
        tied = above_edge.gather(1, self.position_low + 1) - above
        # the query's own point is tied with itself: where the sweep's value there left the band, move it
        high, low = (self.edges.gather(1, p) for p in (self.position_high, self.position_low))
        own = self.own_value
        p_own = torch.exp(own.double() - log_normalizer).nan_to_num(0.0)  # [B, K]
        over, under = own > high, own <= low  # False where no value was picked up (NaN)
        above = above - torch.where(over, p_own, 0.0)
        tied = tied + torch.where(over | under, p_own, 0.0)
        return above.clamp(0.0, 1.0), tied.clamp(0.0, 1.0)


def _finite_or_zero(x: torch.Tensor) -> torch.Tensor:
    return torch.where(torch.isfinite(x), x, torch.zeros_like(x))


def relative_exp(values: torch.Tensor, reference: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(exp(values - reference), reference)`` for values ``(B, n)``, with ``reference (B,)`` their
    maximum (computed unless given; a row of ``-inf`` gets weights 0). Arguments below ``log(tiny)`` are
    raised to it: ``exp`` of them would be a subnormal number, slow to produce, and next to the row's
    maximum (weight 1) they weigh nothing (``e^-86`` in float32)."""
    reference = values.amax(dim=1) if reference is None else reference  # [B]
    shifted = (values - _finite_or_zero(reference)[:, None]).clamp_(min=exp_floor(values.dtype))
    weights = shifted.exp_()
    empty = reference == -math.inf
    if empty.any():
        weights[empty] = 0.0
    return weights, reference


class PoseDistribution:
    """A batch of ``B`` distributions over SO(3) (see the module docstring).

    Subclasses set :attr:`batch_size`, :attr:`dtype` and :attr:`device` (e.g. from their parameter
    tensor) and implement :meth:`unnormalized_log_density`.
    """

    #: False for point regressors (:class:`PointEstimate`): no density, log likelihood or spread
    has_density: bool = True
    batch_size: int
    dtype: torch.dtype
    device: torch.device

    def __init_subclass__(cls, **kwargs):
        """Every method a family defines computes in float32 under autocast (module docstring)."""
        super().__init_subclass__(**kwargs)
        float32_methods(cls)

    # ------------------------------------------------------------------ what a family implements
    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """Log density up to a constant per distribution at ``(K, 3, 3)`` (shared) or ``(B, K, 3, 3)``
        rotations: ``(B, K)``. Differentiable w.r.t. the distribution's parameters."""
        raise NotImplementedError

    def exact_log_normalizer(self) -> torch.Tensor:
        """``log`` of the integral of ``exp(unnormalized_log_density)`` w.r.t. the Haar measure of
        volume ``pi^2``, ``(B,)``, where the family has it in closed form; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form normaliser")

    def exact_mode(self) -> torch.Tensor:
        """The peak of the density ``(B, 3, 3)`` in closed form; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form mode")

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)`` from the continuous density; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} cannot be sampled off the grid")

    # ------------------------------------------------------------------ derived: continuous density
    @property
    def has_exact_density(self) -> bool:
        """True when the family has a closed-form normaliser (and so a continuous log likelihood)."""
        return type(self).exact_log_normalizer is not PoseDistribution.exact_log_normalizer

    def exact_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """The continuous log density ``(B, K)`` (Haar measure of volume ``pi^2``), for families with
        a closed-form normaliser."""
        rotations = self._check_query(rotations)
        return self.unnormalized_log_density(rotations) - self.exact_log_normalizer()[:, None]

    # ------------------------------------------------------------------ checks
    def _check_query(self, rotations: torch.Tensor) -> torch.Tensor:
        check_rotation_matrix(rotations, "rotations")
        if rotations.ndim == 4 and rotations.shape[0] != self.batch_size:
            raise ValueError(
                f"rotations of shape (B, K, 3, 3) must have B = batch size {self.batch_size}, "
                f"got {tuple(rotations.shape)}"
            )
        if rotations.ndim not in (3, 4):
            raise ValueError(f"rotations must have shape (B, K, 3, 3) or (K, 3, 3), got {tuple(rotations.shape)}")
        return rotations.to(device=self.device, dtype=self.dtype)

    def _grid_chunks(self, level: int, multiple: int = 1):
        """``(start, rotations (n, 3, 3))`` chunks of the grid of ``level``, pixel-major (views of the
        grid's rotations, built once per level, dtype and device); ``n`` is ``CHUNK_POINTS`` rounded down
        to a multiple of ``multiple`` (at least ``multiple``), but in the last chunk."""
        grid = _grid_rotations(level, self.dtype, str(self.device))  # [N, 3, 3]
        size = max(multiple, CHUNK_POINTS - CHUNK_POINTS % multiple)
        for start in range(0, len(grid), size):
            yield start, grid[start : start + size]

    # ------------------------------------------------------------------ the grid protocol
    def grid_logsumexp_and_max(self, level: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``logsumexp``, maximum and argmax (pixel-major index) of the unnormalised log density over
        the grid of ``level``, each ``(B,)``; streamed. Differentiable through the logsumexp."""
        return self._sweep(level)

    def _sweep(
        self, level: int, visit: Callable[[torch.Tensor, int, torch.Tensor, torch.Tensor], None] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`grid_logsumexp_and_max` by chunks of the grid; ``visit(values (B, n), start, weights,
        reference)`` sees each chunk's values, the index of its first grid point and the exponentials
        (:func:`relative_exp`) of which the chunk's logsumexp is then made (without gradient)."""
        level = check_streamed_level(level)
        lse = top = arg = None
        # a visitor gets whole groups of fibres (HdrMassAccumulator.add groups pixels at one gamma)
        multiple = 1 if visit is None else HdrMassAccumulator.GROUP_PIXELS * so3_grid_size(level)[1]
        for start, rotations in self._grid_chunks(level, multiple):
            values = self.unnormalized_log_density(rotations)  # [B, n]
            chunk_top, chunk_arg = values.detach().max(dim=1)
            if visit is None:
                chunk_lse = torch.logsumexp(values, dim=1)
            else:  # the visitor's exponentials are the logsumexp's too (not differentiable)
                weights, reference = relative_exp(values.detach(), chunk_top)
                chunk_lse = _finite_or_zero(reference) + weights.sum(dim=1).log()
                visit(values.detach(), start, weights, reference)
            if lse is None:
                lse, top, arg = chunk_lse, chunk_top, chunk_arg + start
            else:
                lse = torch.logaddexp(lse, chunk_lse)
                better = chunk_top > top
                top = torch.where(better, chunk_top, top)
                arg = torch.where(better, chunk_arg + start, arg)
        return lse, top, arg

    def grid_summary(self, level: int, rotations: torch.Tensor | None = None) -> GridSummary:
        """One streamed sweep of the grid of ``level``: log normaliser, maximum and argmax, and for query
        ``rotations`` ``(B, K, 3, 3)`` or ``(K, 3, 3)`` (shared) their nearest grid points, ``log p`` there
        and the highest-density-region masses above and tied (:class:`GridSummary`). Not differentiable.

        The queries' values are read first (``K`` per distribution), so the sweep can bucket every grid
        value against them (:class:`HdrMassAccumulator`): nothing of size ``(B, N)`` or ``(B, K, chunk)``
        is formed. A family with a faster sweep (:class:`~image2sphere.so3.SO3Distribution`) overrides
        :meth:`_summary_sweep` (and :meth:`_values_at_index`, to read the queries as its sweep does).
        """
        level = check_streamed_level(level)
        with torch.no_grad():
            if rotations is None:
                return GridSummary(*(t.detach() for t in self._summary_sweep(level, None)))
            rotations = self._check_query(rotations)
            index = so3_healpix_nearest_index(rotations, level).to(self.device)  # [(B,) K]
            index = index.expand(self.batch_size, -1) if index.ndim == 1 else index  # [B, K]
            values = self._values_at_index(index, level)  # [B, K]
            accumulator = HdrMassAccumulator(values, index, n_gamma=so3_grid_size(level)[1])
            lse, top, arg = (t.detach() for t in self._summary_sweep(level, accumulator))
            above, tied = accumulator.masses(lse)
        return GridSummary(lse, top, arg, index, values - lse[:, None], above, tied)

    def hdr_masses(self, rotations: torch.Tensor, level: int) -> tuple[torch.Tensor, torch.Tensor]:
        """``(mass_above, mass_tied)`` ``(B, K)`` float64 of query ``rotations`` ``(B, K, 3, 3)`` or
        ``(K, 3, 3)`` on the grid of ``level`` (:meth:`grid_summary`). The HDR level of a query is
        ``mass_above + u * mass_tied`` with ``u ~ Uniform(0, 1)`` (docs/evaluation.md#calibration)."""
        summary = self.grid_summary(level, rotations)
        return summary.mass_above, summary.mass_tied

    def _summary_sweep(
        self, level: int, accumulator: HdrMassAccumulator | None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """The sweep behind :meth:`grid_summary`: ``(logsumexp, max, argmax)`` ``(B,)`` each, handing
        every grid value to the ``accumulator`` once."""
        return self._sweep(level, None if accumulator is None else accumulator.add)

    def _values_at_index(self, index: torch.Tensor, level: int) -> torch.Tensor:
        """The unnormalised log density at grid indices ``(B, K)``: ``(B, K)``, as the sweep computes it."""
        rotations = so3_healpix_index_to_matrix(index.reshape(-1), level, dtype=self.dtype).to(self.device)
        return self.unnormalized_log_density(rotations.reshape(*index.shape, 3, 3))

    def log_normalizer(self, level: int) -> torch.Tensor:
        """``logsumexp`` of the unnormalised log density over the grid of ``level``: ``(B,)``."""
        return self.grid_logsumexp_and_max(level)[0]

    def grid_log_density(self, level: int) -> torch.Tensor:
        """Unnormalised log density on the whole grid of ``level``: ``(B, 72 * 8**level)``, pixel-major
        (levels up to ``MAX_DENSE_LEVEL`` and at most ``MAX_OUTPUT_BYTES`` of output)."""
        level = check_level(level, max_level=MAX_DENSE_LEVEL, purpose="a value per grid point",
                            bytes_per_point=torch.finfo(self.dtype).bits // 8)  # fmt: skip
        n = math.prod(so3_grid_size(level))
        nbytes = self.batch_size * n * (torch.finfo(self.dtype).bits // 8)
        if nbytes > MAX_OUTPUT_BYTES:
            raise ValueError(
                f"a value per grid point for a batch of {self.batch_size} at level {level} needs "
                f"{nbytes / 2**30:.1f} GiB (> {MAX_OUTPUT_BYTES / 2**30:.1f} GiB); use a smaller batch or level"
            )
        return torch.cat([self.unnormalized_log_density(r) for _, r in self._grid_chunks(level)], dim=1)

    def log_prob_grid(self, level: int) -> torch.Tensor:
        """Log-softmax over the grid of ``level``: ``(B, N)`` (the grid probabilities ``log p_i``)."""
        return torch.log_softmax(self.grid_log_density(level), dim=-1)

    def log_prob_at_index(
        self, index: torch.Tensor, level: int, log_normalizer: torch.Tensor | None = None
    ) -> torch.Tensor:
        """``log p_i`` at grid indices ``(B, K)`` or ``(K,)``: ``(B, K)``."""
        level = check_streamed_level(level)
        index = torch.as_tensor(index, device=self.device)
        shape = index.shape
        rotations = so3_healpix_index_to_matrix(index.reshape(-1), level, dtype=self.dtype).to(self.device)
        rotations = rotations.reshape(*shape, 3, 3)
        if log_normalizer is None:
            log_normalizer = self.log_normalizer(level)
        return self.unnormalized_log_density(rotations) - log_normalizer[:, None]

    def log_density(
        self, rotations: torch.Tensor, level: int, log_normalizer: torch.Tensor | None = None
    ) -> torch.Tensor:
        """Log density by the grid protocol at ``(B, K, 3, 3)`` or ``(K, 3, 3)`` rotations: ``(B, K)``,
        ``log(p_nearest * N / pi^2)``. ``log_normalizer``: :meth:`log_normalizer` of ``level`` when
        the caller already has it."""
        level = check_streamed_level(level)
        rotations = self._check_query(rotations)
        index = so3_healpix_nearest_index(rotations, level).to(self.device)  # [(B,) K]
        n_points = math.prod(so3_grid_size(level))
        return self.log_prob_at_index(index, level, log_normalizer) + math.log(n_points) + LOG_UNIFORM_DENSITY

    def nll_on_grid(self, rotation: torch.Tensor, level: int) -> torch.Tensor:
        """Cross-entropy ``(B,)`` against the grid point nearest each ``rotation (B, 3, 3)``: the loss of
        a method trained as a classifier over the grid (I2S)."""
        index = so3_healpix_nearest_index(rotation.detach(), level).to(self.device)  # [B]
        return -self.log_prob_at_index(index[:, None], level)[:, 0]

    # ------------------------------------------------------------------ point estimate and samples
    def mode(self, level: int, refine: bool = False) -> torch.Tensor:
        """Most likely rotation ``(B, 3, 3)``: the grid argmax; with ``refine`` the family's closed-form
        peak where it has one (else the grid argmax)."""
        if refine:
            try:
                return self.exact_mode()
            except NotImplementedError:
                pass
        _, _, arg = self.grid_logsumexp_and_max(level)
        return so3_healpix_index_to_matrix(arg, level, dtype=self.dtype).to(self.device)

    def sample(
        self, n: int, level: int, generator: torch.Generator | None = None, return_index: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """``n`` grid rotations per distribution ``(B, n, 3, 3)`` drawn from the grid softmax (the grid
        protocol's distribution); with ``return_index`` also their indices ``(B, n)``."""
        check_int("n", n, 1)
        level = check_streamed_level(level)
        with torch.no_grad():
            lse = self.log_normalizer(level)
            # Gumbel-max per chunk for each of the n draws: exact, no (B, N) tensor
            best = torch.full((self.batch_size, n), -math.inf, dtype=self.dtype, device=self.device)
            index = torch.zeros((self.batch_size, n), dtype=torch.long, device=self.device)
            for start, rotations in self._grid_chunks(level):
                log_p = self.unnormalized_log_density(rotations) - lse[:, None]  # [B, c]
                u = torch.rand((*log_p.shape, n), generator=generator, dtype=self.dtype, device=self.device)
                gumbel = log_p[..., None] - torch.log(-torch.log(u.clamp_min(1e-30)))  # [B, c, n]
                top, arg = gumbel.max(dim=1)  # [B, n]
                better = top > best
                best = torch.where(better, top, best)
                index = torch.where(better, arg + start, index)
        rotations = so3_healpix_index_to_matrix(index, level, dtype=self.dtype).to(self.device)
        return (rotations, index) if return_index else rotations

    def points_above(
        self, threshold: float | torch.Tensor, level: int, max_points: int = 2_000_000
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Grid points with ``p_i >= threshold`` (a number, or one per distribution), per distribution:
        ``(index (K,), prob (K,))`` in decreasing probability; ``ValueError`` beyond ``max_points``."""
        thresholds = check_threshold(threshold).reshape(-1)
        if thresholds.numel() not in (1, self.batch_size):
            raise ValueError(
                f"threshold must be a number or one per distribution ({self.batch_size},), got {thresholds.numel()}"
            )
        log_t = thresholds.expand(self.batch_size).log().to(self.device, self.dtype)
        level = check_streamed_level(level)
        kept: list[list[tuple[torch.Tensor, torch.Tensor]]] = [[] for _ in range(self.batch_size)]
        with torch.no_grad():
            lse = self.log_normalizer(level)
            for start, rotations in self._grid_chunks(level):
                log_p = self.unnormalized_log_density(rotations) - lse[:, None]  # [B, c]
                for b in range(self.batch_size):
                    where = torch.nonzero(log_p[b] >= log_t[b]).flatten()
                    if len(where):
                        kept[b].append((where + start, log_p[b, where].exp()))
                        if sum(len(i) for i, _ in kept[b]) > max_points:
                            raise ValueError(
                                f"more than max_points={max_points} points pass threshold {float(log_t[b].exp()):g} "
                                f"at level {level}; raise it"
                            )
        out = []
        for parts in kept:
            if not parts:
                out.append((torch.zeros(0, dtype=torch.long, device=self.device), torch.zeros(0, dtype=self.dtype)))
                continue
            index, prob = torch.cat([i for i, _ in parts]), torch.cat([p for _, p in parts])
            order = torch.argsort(prob, descending=True)
            out.append((index[order], prob[order]))
        return out

    def max_prob(self, level: int) -> torch.Tensor:
        """The largest grid probability per distribution, ``(B,)`` float64 on the CPU."""
        with torch.no_grad():
            lse, top, _ = self.grid_logsumexp_and_max(level)
        return (top - lse).double().exp().cpu()

    def default_threshold(self, level: int) -> torch.Tensor:
        """``min(10 / N, max_i p_i)`` per distribution ``(B,)`` (the plots' and :meth:`modes`' default)."""
        n_points = math.prod(so3_grid_size(check_streamed_level(level)))
        return torch.clamp(self.max_prob(level) * (1 - 1e-6), max=10.0 / n_points)

    def modes(
        self,
        level: int,
        k: int = 5,
        radius_deg: float = 20.0,
        threshold: float | None = None,
        refine: bool = False,
        mass_level: int = 4,
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Up to ``k`` separate modes per distribution and the probability mass within ``radius_deg``
        of each (greedy non-maximum suppression on the grid of ``level``; mass on the grid of
        ``min(level, mass_level)``, each point counted for its nearest mode), in decreasing mass.
        With ``refine`` each mode is moved off the grid by :meth:`_refine_modes` (the families that
        can; the others return the grid modes)."""
        level = check_streamed_level(level)
        coarse = min(level, check_level(mass_level, "mass_level"))
        check_level(coarse, "mass_level", max_level=MAX_DENSE_LEVEL, purpose="the probability mass of modes",
                    bytes_per_point=40)  # fmt: skip
        check_int("k", k, 1)
        if isinstance(radius_deg, bool) or not isinstance(radius_deg, numbers.Real) or not 0 < radius_deg < 180:
            raise ValueError(f"radius_deg must be in (0, 180), got {radius_deg!r}")
        threshold = self.default_threshold(level) if threshold is None else check_threshold(threshold)
        min_trace = 1 + 2 * math.cos(math.radians(radius_deg))
        grid = so3_healpix_grid(coarse, dtype=self.dtype).reshape(-1, 9).to(self.device)  # [N, 9]
        with torch.no_grad():
            probs = self.log_prob_grid(coarse).exp()  # [B, N]
        out = []
        for b, (index, _) in enumerate(self.points_above(threshold, level)):
            flat = so3_healpix_index_to_matrix(index, level, dtype=self.dtype).reshape(-1, 9).to(self.device)
            free = torch.ones(len(flat), dtype=torch.bool, device=self.device)
            chosen = []
            while free.any() and len(chosen) < k:
                i = int(torch.nonzero(free)[0])
                free &= flat @ flat[i] < min_trace
                chosen.append(i)
            if not chosen:
                out.append((flat.new_empty(0, 3, 3), flat.new_empty(0)))
                continue
            best, owner = (grid @ flat[chosen].T).max(dim=1)
            within = best >= min_trace
            mass = torch.zeros(len(chosen), dtype=probs.dtype, device=self.device)
            mass.index_add_(0, owner[within], probs[b][within])
            centres = flat[chosen].reshape(-1, 3, 3)
            if refine:
                centres = self._refine_modes(b, centres, level)
            order = torch.argsort(mass, descending=True)
            out.append((centres[order], mass[order]))
        return out

    def _refine_modes(self, b: int, centres: torch.Tensor, level: int) -> torch.Tensor:
        """Grid modes ``(k, 3, 3)`` of distribution ``b`` moved off the grid; here: unchanged."""
        return centres


float32_methods(PoseDistribution)  # the base class's own methods (subclasses: __init_subclass__)


class PointEstimate(PoseDistribution):
    """The output of a point regressor: one rotation per image and no density.

    :meth:`mode` and :meth:`sample` return the rotation; every density method raises
    :class:`DensityNotAvailable`, and evaluations report the log likelihood and the spread as not
    available.
    """

    has_density = False

    def __init__(self, rotation: torch.Tensor):
        check_rotation_matrix(rotation, "rotation", atol=1e-3)
        if rotation.ndim != 3:
            raise ValueError(f"rotation must have shape (B, 3, 3), got {tuple(rotation.shape)}")
        self.rotation = rotation
        self.batch_size, self.dtype, self.device = rotation.shape[0], rotation.dtype, rotation.device

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        raise DensityNotAvailable(f"{type(self).__name__} is a point estimate: it has no density")

    def exact_mode(self) -> torch.Tensor:
        return self.rotation

    def mode(self, level: int | None = None, refine: bool = False) -> torch.Tensor:
        return self.rotation

    def sample(self, n: int, level: int | None = None, generator=None, return_index: bool = False):
        if return_index:
            raise DensityNotAvailable("a point estimate has no grid indices")
        return self.rotation[:, None].expand(-1, n, -1, -1)

    def modes(self, level: int = 5, k: int = 5, **_) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return [(r[None], torch.ones(1, dtype=self.dtype, device=self.device)) for r in self.rotation]
