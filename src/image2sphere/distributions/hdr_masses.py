"""Highest-density-region masses of grid points, streamed (docs/evaluation.md#calibration).

For a query rotation with nearest grid point ``t`` on the grid of a level, the grid mass strictly above
it, ``sum_{i: p_i > p_t} p_i``, and the mass tied with it, ``sum_{i: p_i == p_t} p_i`` (``t`` itself
included). "Tied" means equal up to a relative tolerance in log space (:func:`tie_tolerance`), so that
values equal in exact arithmetic but computed by two code paths still tie. :class:`HdrMassAccumulator`
collects them from the chunks of one sweep of the grid (the sweep that also gives the log normaliser,
the maximum and the argmax: :meth:`~image2sphere.distributions.grid_protocol.GridProtocol.grid_summary`),
for any family. Nothing here knows a distribution: it sees grid values only.
"""

from __future__ import annotations

import math

import torch

from image2sphere.checks import ConfigError
from image2sphere.so3.grid_eval import exp_floor

__all__ = ["HdrMassAccumulator", "finite_or_zero", "relative_exp", "tie_tolerance"]


def tie_tolerance(values: torch.Tensor) -> torch.Tensor:
    """Half-width of the band of log densities that count as tied with ``values`` (any shape, same shape
    out): ``128 * eps(dtype) * max(1, |value|)`` (1.5e-5 relative in float32, 2.8e-14 in float64).

    Two grid values that are equal in exact arithmetic (a uniform or piecewise-constant density) can
    differ in the last bits when one is computed on a grid chunk and the other at a single query; the
    band makes them tie. For a smooth density it holds a negligible mass besides the query's own point.
    """
    eps = torch.finfo(values.dtype).eps
    return 128 * eps * values.abs().clamp_min(1.0)


def finite_or_zero(x: torch.Tensor) -> torch.Tensor:
    return torch.where(torch.isfinite(x), x, torch.zeros_like(x))


def relative_exp(values: torch.Tensor, reference: torch.Tensor | None = None) -> tuple[torch.Tensor, torch.Tensor]:
    """``(exp(values - reference), reference)`` for values ``(B, n)``, with ``reference (B,)`` their
    maximum (computed unless given; a row of ``-inf`` gets weights 0). Arguments below ``log(tiny)`` are
    raised to it: ``exp`` of them would be a subnormal number, slow to produce, and next to the row's
    maximum (weight 1) they weigh nothing (``e^-86`` in float32)."""
    reference = values.amax(dim=1) if reference is None else reference  # [B]
    shifted = (values - finite_or_zero(reference)[:, None]).clamp_(min=exp_floor(values.dtype))
    weights = shifted.exp_()
    empty = reference == -math.inf
    if empty.any():
        weights[empty] = 0.0
    return weights, reference


class HdrMassAccumulator:
    """Streams chunks of grid values into, for each of ``K`` query values per distribution, the grid
    mass above the query and the mass tied with it (see
    :class:`~image2sphere.distributions.grid_protocol.GridSummary`), without a ``(B, K, chunk)`` comparison.

    Args:
        query_values: ``(B, K)``, the unnormalised log density at each query's grid point, as read at the
            query (:meth:`~image2sphere.distributions.grid_protocol.GridProtocol._values_at_index`).
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
            raise ConfigError(
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
