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

A family subclasses :class:`PoseDistribution` and implements :meth:`~PoseDistribution.unnormalized_log_density`
(and, where the family has them, :meth:`~PoseDistribution.exact_log_normalizer`,
:meth:`~PoseDistribution.exact_mode` and :meth:`~PoseDistribution.exact_sample`). Everything else
(grid reductions, nearest-point log density, modes, sampling on the grid, points above a threshold)
comes from this class. A point regressor subclasses :class:`PointEstimate` instead: it has a mode
and no density.
"""

from __future__ import annotations

import functools
import math
import numbers

import torch

from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    check_level,
    so3_grid_size,
    so3_healpix_grid,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)
from image2sphere.so3.grid_eval import MAX_OUTPUT_BYTES, check_streamed_level
from image2sphere.so3.rotations import check_rotation_matrix

__all__ = ["LOG_UNIFORM_DENSITY", "DensityNotAvailable", "PointEstimate", "PoseDistribution", "check_threshold"]

LOG_UNIFORM_DENSITY = -math.log(math.pi**2)  # -2.2894
# grid rotations per chunk of the generic sweep: B x CHUNK values at a time
CHUNK_POINTS = 1 << 16


@functools.lru_cache(maxsize=2)
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

    def _grid_chunks(self, level: int):
        """``(start, rotations (n, 3, 3))`` chunks of the grid of ``level``, pixel-major (views of the
        grid's rotations, built once per level, dtype and device)."""
        grid = _grid_rotations(level, self.dtype, str(self.device))  # [N, 3, 3]
        for start in range(0, len(grid), CHUNK_POINTS):
            yield start, grid[start : start + CHUNK_POINTS]

    # ------------------------------------------------------------------ the grid protocol
    def grid_logsumexp_and_max(self, level: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``logsumexp``, maximum and argmax (pixel-major index) of the unnormalised log density over
        the grid of ``level``, each ``(B,)``; streamed. Differentiable through the logsumexp."""
        level = check_streamed_level(level)
        lse = top = arg = None
        for start, rotations in self._grid_chunks(level):
            values = self.unnormalized_log_density(rotations)  # [B, n]
            chunk_lse = torch.logsumexp(values, dim=1)
            chunk_top, chunk_arg = values.detach().max(dim=1)
            if lse is None:
                lse, top, arg = chunk_lse, chunk_top, chunk_arg + start
            else:
                lse = torch.logaddexp(lse, chunk_lse)
                better = chunk_top > top
                top = torch.where(better, chunk_top, top)
                arg = torch.where(better, chunk_arg + start, arg)
        return lse, top, arg

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
        if isinstance(n, bool) or not isinstance(n, int) or n < 1:
            raise ValueError(f"n must be a positive integer, got {n!r}")
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
        if isinstance(k, bool) or not isinstance(k, int) or k < 1:
            raise ValueError(f"k must be a positive integer, got {k!r}")
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
