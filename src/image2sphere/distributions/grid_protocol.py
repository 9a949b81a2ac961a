"""The grid protocol: how every density family is scored, written once against the interface
(:class:`~image2sphere.distributions.base.PoseDistribution`), so that it works for any family.

* A family's (unnormalised) log density is evaluated on the HEALPix SO(3) grid of a level and put
  through a softmax, ``p_i``; the density at ``R`` is ``p_nearest(R) * N / pi^2`` (Haar measure of
  volume ``pi^2``: a uniform distribution has log density :data:`LOG_UNIFORM_DENSITY`) and the point
  estimate is the grid argmax. The grid is swept in chunks of :data:`CHUNK_POINTS` rotations (never a
  ``(B, N)`` tensor unless asked for one).
* From those sweeps: the log normaliser, maximum and argmax, log densities at grid points and at
  rotations, modes (greedy non-maximum suppression), exact sampling from the grid softmax (Gumbel-max
  per chunk), the points above a probability threshold, and the highest-density-region masses of query
  rotations (:meth:`GridProtocol.grid_summary`, :mod:`~image2sphere.distributions.hdr_masses`), all in
  one streamed sweep.

:class:`GridProtocol` is a mixin of :class:`~image2sphere.distributions.base.PoseDistribution`: it uses
only the interface (``batch_size``, ``dtype``, ``device``, ``unnormalized_log_density``,
``exact_mode``, ``_check_query``). A family with a faster way to compute part of it overrides only
that part: the Fourier family (:class:`~image2sphere.distributions.fourier.SO3Distribution`) overrides
the sweeps (:meth:`~GridProtocol.grid_logsumexp_and_max`, :meth:`~GridProtocol._summary_sweep`,
:meth:`~GridProtocol.log_normalizer`), the values at grid points (:meth:`~GridProtocol._values_at_index`,
:meth:`~GridProtocol.grid_log_density`), :meth:`~GridProtocol.points_above`, :meth:`~GridProtocol.sample`,
and the refinement of modes (:meth:`~GridProtocol.mode`, :meth:`~GridProtocol._refine_modes`).
"""

from __future__ import annotations

import math
import numbers
from collections.abc import Callable
from typing import NamedTuple

import torch

from image2sphere.batch_progress import report as report_progress
from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.hdr_masses import HdrMassAccumulator, finite_or_zero, relative_exp
from image2sphere.precision import constant_cache, float32_methods
from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    check_level,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)
from image2sphere.so3.grid_eval import MAX_OUTPUT_BYTES, check_streamed_level

__all__ = ["CHUNK_POINTS", "LOG_UNIFORM_DENSITY", "GridProtocol", "GridSummary", "check_threshold"]

LOG_UNIFORM_DENSITY = -math.log(math.pi**2)  # -2.2894
# grid rotations per chunk of the generic sweep: B x CHUNK values at a time
CHUNK_POINTS = 1 << 16


@constant_cache(maxsize=2)
def _grid_rotations(level: int, dtype: torch.dtype, device: str) -> torch.Tensor:
    """The rotations of the grid of ``level`` ``(N, 3, 3)``, pixel-major (85 MB at level 5 in float32)."""
    return so3_healpix_grid(level, dtype=dtype).to(device)


def check_threshold(threshold, name: str = "threshold") -> torch.Tensor:
    """A probability threshold (a number, or a tensor of them) as a float64 tensor; ``ValueError``
    unless every value is a probability in ``(0, 1]``."""
    message = f"{name} must be > 0 and <= 1 (a probability in (0, 1]), got {{!r}}"
    if isinstance(threshold, (bool, str)) or threshold is None:
        raise ConfigError(message.format(threshold))
    try:
        values = torch.as_tensor(threshold, dtype=torch.float64).detach().cpu()
    except (TypeError, ValueError, RuntimeError):
        raise ConfigError(message.format(threshold)) from None
    if not ((values > 0) & (values <= 1)).all():  # NaN fails both comparisons
        raise ConfigError(message.format(threshold if values.numel() == 1 else values.tolist()))
    return values


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


class GridProtocol:
    """The grid protocol's methods (module docstring) for a batch of ``B`` distributions over SO(3) that
    has ``batch_size``, ``dtype``, ``device``, ``unnormalized_log_density``, ``exact_mode`` and
    ``_check_query`` (:class:`~image2sphere.distributions.base.PoseDistribution`)."""

    def _grid_chunks(self, level: int):
        """``(start, rotations (n, 3, 3))`` chunks of the grid of ``level``, pixel-major (views of the
        grid's rotations, built once per level, dtype and device). ``n`` is ``CHUNK_POINTS`` rounded down
        to whole groups of fibres (what :meth:`HdrMassAccumulator.add` takes), but in the last chunk: every
        sweep of a level sees the same chunks, so a family that keeps its values per query tensor
        (:class:`~.implicit.ImplicitDistribution`) evaluates the grid once for all of them."""
        grid = _grid_rotations(level, self.dtype, str(self.device))  # [N, 3, 3]
        multiple = HdrMassAccumulator.GROUP_PIXELS * so3_grid_size(level)[1]
        size = max(multiple, CHUNK_POINTS - CHUNK_POINTS % multiple)
        chunks = -(-len(grid) // size)
        for start in range(0, len(grid), size):
            report_progress(start // size, chunks, f"grid {level}", "chunks")  # a long test batch moves
            yield start, grid[start : start + size]

    # ------------------------------------------------------------------ sweeps and values
    def grid_logsumexp_and_max(self, level: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``logsumexp``, maximum and argmax (pixel-major index) of the unnormalised log density over
        the grid of ``level``, each ``(B,)``; streamed. Differentiable through the logsumexp."""
        return self._sweep(level)

    def _sweep(
        self, level: int, visit: Callable[[torch.Tensor, int, torch.Tensor, torch.Tensor], None] | None = None
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`grid_logsumexp_and_max` by chunks of the grid; ``visit(values (B, n), start, weights,
        reference)`` sees each chunk's values, the index of its first grid point and the exponentials
        (:func:`~.hdr_masses.relative_exp`) of which the chunk's logsumexp is then made (without gradient)."""
        level = check_streamed_level(level)
        lse = top = arg = None
        for start, rotations in self._grid_chunks(level):  # whole groups of fibres, as a visitor needs
            values = self.unnormalized_log_density(rotations)  # [B, n]
            chunk_top, chunk_arg = values.detach().max(dim=1)
            if visit is None:
                chunk_lse = torch.logsumexp(values, dim=1)
            else:  # the visitor's exponentials are the logsumexp's too (not differentiable)
                weights, reference = relative_exp(values.detach(), chunk_top)
                chunk_lse = finite_or_zero(reference) + weights.sum(dim=1).log()
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
        value against them (:class:`~.hdr_masses.HdrMassAccumulator`): nothing of size ``(B, N)`` or
        ``(B, K, chunk)`` is formed. A family with a faster sweep (:class:`~.fourier.SO3Distribution`)
        overrides :meth:`_summary_sweep` (and :meth:`_values_at_index`, to read the queries as its sweep does).
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
        """The unnormalised log density at grid indices ``(B, K)`` or ``(K,)``: ``(B, K)``, as the sweep
        computes it (differentiable)."""
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
            raise ConfigError(
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
        """``log p_i`` at grid indices ``(B, K)`` or ``(K,)``: ``(B, K)``, streamed. ``log_normalizer``
        ``(B,)``: :meth:`log_normalizer` of ``level`` when the caller already has it (e.g. from
        :meth:`grid_logsumexp_and_max`), so the grid is not swept a second time."""
        level = check_streamed_level(level)
        index = torch.as_tensor(index, device=self.device)
        if log_normalizer is None:
            log_normalizer = self.log_normalizer(level)
        return self._values_at_index(index, level) - log_normalizer[:, None]

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
        with torch.no_grad():  # an index: nothing to differentiate
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
        log_t = self._thresholds(threshold).log().to(self.device, self.dtype)
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
                            raise ConfigError(
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

    def _thresholds(self, threshold: float | torch.Tensor) -> torch.Tensor:
        """:meth:`points_above`'s ``threshold``, checked, one per distribution: ``(B,)`` float64."""
        thresholds = check_threshold(threshold).reshape(-1)
        if thresholds.numel() not in (1, self.batch_size):
            raise ConfigError(
                f"threshold must be a number or one per distribution ({self.batch_size},), got {thresholds.numel()}"
            )
        return thresholds.expand(self.batch_size)

    def max_prob(self, level: int) -> torch.Tensor:
        """The largest grid probability per distribution, ``(B,)`` float64 on the CPU."""
        with torch.no_grad():
            lse, top, _ = self.grid_logsumexp_and_max(level)
        return (top - lse).double().exp().cpu()

    def default_threshold(self, level: int) -> torch.Tensor:
        """``min(10 / N, max_i p_i)`` per distribution ``(B,)`` (the plots' and :meth:`modes`' default):
        ten times the uniform probability, lowered to the top probability for flat distributions so
        that the top point always passes."""
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
        """Up to ``k`` separate modes per distribution and the probability mass around each.

        Modes: greedy non-maximum suppression on the grid of ``level``. The most probable remaining
        point is a mode and the points within ``radius_deg`` of it leave the search. Only points
        with ``p_i >= threshold`` are candidates (default :meth:`default_threshold`: ten times the
        uniform probability, so that flat regions give no modes, or the top probability when that
        is lower). Mass: the probability, on the whole grid of ``min(level, mass_level)``, of the
        points within ``radius_deg`` of a mode, each counted for its nearest mode. Returned in
        decreasing mass, each as ``(rotations (k', 3, 3), mass (k',))``. With ``refine`` each mode is
        moved off the grid by :meth:`_refine_modes` (the Fourier family: gradient ascent on its series,
        as its ``mode``; the others return the grid modes).

        An explicit ``threshold`` must be a probability in ``(0, 1]``. When no grid point of a
        distribution reaches it, that distribution has no modes: its entry is ``(rotations (0, 3, 3),
        mass (0,))`` (compare with :meth:`max_prob`). ``mass_level`` is at most ``MAX_DENSE_LEVEL``.
        """
        level = check_streamed_level(level)
        coarse = min(level, check_level(mass_level, "mass_level"))
        check_level(coarse, "mass_level", max_level=MAX_DENSE_LEVEL, purpose="the probability mass of modes",
                    bytes_per_point=40)  # fmt: skip
        check_int("k", k, 1)
        if isinstance(radius_deg, bool) or not isinstance(radius_deg, numbers.Real) or not 0 < radius_deg < 180:
            raise ConfigError(f"radius_deg must be in (0, 180), got {radius_deg!r}")
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


float32_methods(GridProtocol)  # its methods compute in float32 under autocast (like the families')
