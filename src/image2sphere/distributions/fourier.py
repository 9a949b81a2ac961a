"""The Fourier family (I2S's output): distributions over SO(3) given by a signal in the flat Wigner layout.

Conventions (docs/conventions.md#densities)
-------------------------------------------
* The model's signal ``f`` (logits) is evaluated on the HEALPix SO(3) grid of a level and put
  through a softmax: ``p_i = softmax(f(R_i))`` over the ``N`` grid points (the grid protocol,
  :mod:`image2sphere.distributions.grid_protocol`).
* The density at ``R`` w.r.t. the Haar measure normalised to total volume ``pi^2`` (IPDF's
  convention) is ``p_nearest(R) * N / pi^2``; a uniform distribution has log density
  ``-log(pi^2) = -2.2894``.
* Grid values and indices are in pixel-major order (:mod:`image2sphere.so3.grid`).

:class:`SO3Distribution` overrides only what it computes differently from the grid protocol: the
sweeps and the values at grid points come from the grid evaluator
(:class:`~image2sphere.so3.grid_eval.HealpixGridEvaluator`), :meth:`~SO3Distribution.points_above` and
:meth:`~SO3Distribution.sample` go through the gamma-marginals of the pixels, and modes are refined
by gradient ascent on the series.
"""

from __future__ import annotations

import math
import numbers

import torch
from e3nn import o3

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution, check_temperature
from image2sphere.rotation_sets import check_target_mask, fill_padding
from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    check_level,
    so3_grid_size,
    so3_healpix_index_to_matrix,
    so3_healpix_nearest_index,
)
from image2sphere.so3.grid_eval import MAX_OUTPUT_BYTES, check_streamed_level, get_grid_evaluator
from image2sphere.so3.rotations import matrix_to_angles, rotvec_to_matrix
from image2sphere.so3.wigner import check_lmax, default_dtype, flat_wigner, n_so3_coeffs, so3_blocks, wigner_D

__all__ = ["SO3Distribution", "fourier_grid_nll", "fourier_grid_set_nll"]


def fourier_grid_nll(coeffs: torch.Tensor, lmax: int, rotation: torch.Tensor, level: int) -> torch.Tensor:
    """I2S's training loss ``(B,)``: the cross-entropy of the grid softmax of the signal ``coeffs
    (B, n_so3_coeffs(lmax))`` at ``level`` against the grid point nearest each ``rotation (B, 3, 3)``,
    ``logsumexp_i f(R_i) - f(R_label)``, streamed. Not-finite coefficients give a not-finite loss
    (for the caller to report) rather than an error here."""
    ev = get_grid_evaluator(lmax, check_streamed_level(level), coeffs.dtype, coeffs.device)
    index = so3_healpix_nearest_index(rotation.detach(), level).to(coeffs.device)  # [B]
    return ev.logsumexp(coeffs) - ev.logits_at(coeffs, index[:, None])[:, 0]


def fourier_grid_set_nll(
    coeffs: torch.Tensor, lmax: int, rotations: torch.Tensor, mask: torch.Tensor, level: int
) -> torch.Tensor:
    """:func:`fourier_grid_nll` averaged over each image's equivalent rotations ``(B,)``: ``rotations
    (B, M, 3, 3)``, real where ``mask (B, M)`` (the first of each image among them,
    :func:`~image2sphere.rotation_sets.check_target_mask`); ``logsumexp_i f(R_i) - mean_k f(R_k)`` with the grid
    point nearest each ``R_k``. The normaliser is computed once per image, not once per rotation."""
    check_target_mask(mask)
    B, M = mask.shape
    ev = get_grid_evaluator(lmax, check_streamed_level(level), coeffs.dtype, coeffs.device)
    real = mask.to(coeffs.device)
    filled = fill_padding(rotations, mask)  # padding (possibly NaN) read as the image's first rotation
    index = so3_healpix_nearest_index(filled.detach().reshape(B * M, 3, 3), level).reshape(B, M).to(coeffs.device)
    values = ev.logits_at(coeffs, index)  # [B, M]
    mean = (values * real).sum(1) / real.sum(1)  # [B]
    return ev.logsumexp(coeffs) - mean


class SO3Distribution(PoseDistribution):
    """A batch of distributions over SO(3) given by Fourier coefficients.

    Args:
        coeffs: ``(B, n_so3_coeffs(lmax))`` in the flat Wigner layout (the network's output); finite.
        lmax: the band limit.

    Methods that evaluate the signal on a grid take its ``level``, checked before anything is built:
    ``0..MAX_STREAMED_LEVEL`` (7) for the streamed methods, ``0..MAX_DENSE_LEVEL`` (6) where a value
    per grid point is returned (:meth:`grid_logits`, :meth:`log_prob_grid`) or gathered
    (``mass_level`` of :meth:`modes`).
    """

    def __init__(self, coeffs: torch.Tensor, lmax: int):
        self.lmax = check_lmax(lmax)
        n = n_so3_coeffs(self.lmax)
        if not isinstance(coeffs, torch.Tensor) or coeffs.ndim != 2 or coeffs.shape[1] != n:
            shape = tuple(coeffs.shape) if isinstance(coeffs, torch.Tensor) else type(coeffs).__name__
            raise ConfigError(f"coeffs must have shape (batch, {n}) for lmax={self.lmax}, got {shape}")
        if not coeffs.is_floating_point():
            raise ConfigError(f"coeffs must be floating point, got {coeffs.dtype}")
        if not torch.isfinite(coeffs).all():
            bad = torch.nonzero(~torch.isfinite(coeffs.detach()).all(dim=1)).flatten().tolist()
            listed = ", ".join(map(str, bad[:10])) + (", ..." if len(bad) > 10 else "")
            raise ConfigError(
                f"coeffs contain NaN or infinite values in {len(bad)} of {coeffs.shape[0]} distributions "
                f"(batch entries {listed}); the network's output is not finite: check its input and weights"
            )
        self.coeffs = coeffs
        self.dtype, self.device = coeffs.dtype, coeffs.device

    @property
    def batch_size(self) -> int:
        return self.coeffs.shape[0]

    # ------------------------------------------------------------------ the PoseDistribution interface
    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """The signal (logits) at rotations ``(B, K, 3, 3)`` or ``(K, 3, 3)``: ``(B, K)``."""
        return self.logits(rotations)

    def tempered(self, temperature: float) -> SO3Distribution:
        """``p ** (1 / temperature)``, renormalised: the signal is linear in its coefficients, so this is the
        same family with the coefficients divided by the temperature (exact, on the fast path)."""
        temperature = check_temperature(temperature)
        return self if temperature == 1.0 else SO3Distribution(self.coeffs / temperature, self.lmax)

    def grid_logsumexp_and_max(self, level: int) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """``logsumexp``, maximum and argmax of the signal over the grid of ``level`` (fast path)."""
        return self._evaluator(level).logsumexp_and_max(self.coeffs)

    def grid_log_density(self, level: int) -> torch.Tensor:
        return self.grid_logits(level)

    def _summary_sweep(self, level: int, accumulator) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """:meth:`grid_summary`'s sweep on the fast path: the evaluator's logsumexp-and-max pass, which
        hands each chunk of gamma fibres, with the exponentials it computes anyway, to the accumulator."""
        visit = None if accumulator is None else accumulator.add_fibres
        return self._evaluator(level).logsumexp_and_max(self.coeffs.detach(), visit=visit)

    def _values_at_index(self, index: torch.Tensor, level: int) -> torch.Tensor:
        """The signal at grid indices ``(B, K)`` or ``(K,)``: ``(B, K)``, from the evaluator's tables (as its
        sweep computes it), differentiable."""
        return self._evaluator(level).logits_at(self.coeffs, index)

    def _evaluator(self, level: int):
        return get_grid_evaluator(self.lmax, check_streamed_level(level), self.coeffs.dtype, self.coeffs.device)

    # ------------------------------------------------------------------ values
    def logits(self, rotations: torch.Tensor) -> torch.Tensor:
        """Signal at arbitrary rotations ``(B, K, 3, 3)`` or ``(K, 3, 3)`` (shared): ``(B, K)``."""
        rotations = self._check_query(rotations)
        D = flat_wigner(self.lmax, rotations)  # [(B,) K, n]
        if rotations.ndim == 3:
            return torch.einsum("kn,bn->bk", D, self.coeffs)
        return torch.einsum("bkn,bn->bk", D, self.coeffs)

    def grid_logits(self, level: int) -> torch.Tensor:
        """Signal on the whole grid of ``level``: ``(B, 72 * 8**level)``, pixel-major.

        Levels up to :data:`~image2sphere.so3.grid.MAX_DENSE_LEVEL`, and at most
        :data:`~image2sphere.so3.grid_eval.MAX_OUTPUT_BYTES` of output (checked before any work).
        """
        level = check_level(level, max_level=MAX_DENSE_LEVEL, purpose="full-grid logits",
                            bytes_per_point=self.coeffs.element_size())  # fmt: skip
        nbytes = self.batch_size * math.prod(so3_grid_size(level)) * self.coeffs.element_size()
        if nbytes > MAX_OUTPUT_BYTES:
            raise ConfigError(
                f"full-grid logits for a batch of {self.batch_size} at level {level} need {nbytes / 2**30:.1f} GiB "
                f"(> {MAX_OUTPUT_BYTES / 2**30:.1f} GiB); use a smaller batch, a lower level or the streamed "
                "methods (log_normalizer, log_prob_at_index, points_above)"
            )
        return self._evaluator(level).logits(self.coeffs)

    def log_normalizer(self, level: int) -> torch.Tensor:
        """``logsumexp`` of the signal over the grid, ``(B,)``, streamed (no ``(B, N)`` tensor)."""
        return self._evaluator(level).logsumexp(self.coeffs)

    # ------------------------------------------------------------------ point estimate and samples
    def mode(self, level: int, refine: bool = False, steps: int = 100, lr: float | None = None) -> torch.Tensor:
        """Most likely rotation ``(B, 3, 3)``: the grid argmax, optionally refined.

        With ``refine=True`` the rotation ``R0 @ exp(w)`` is moved by gradient ascent on the
        band-limited signal itself (Adam on ``w``, learning rate decayed linearly over ``steps``;
        default ``lr`` is a tenth of the grid spacing), so the estimate is no longer tied to the grid.
        ``steps`` is an integer >= 0 (0: the grid argmax is returned unrefined); ``lr`` a finite number > 0.
        """
        check_int("steps", steps, 0, note=" (0: no refinement)")
        if lr is not None and (isinstance(lr, bool) or not isinstance(lr, numbers.Real) or not 0 < lr < math.inf):
            raise ConfigError(f"lr must be a finite number > 0 (or None: a tenth of the grid spacing), got {lr!r}")
        R0 = super().mode(level)
        if not refine or steps == 0:
            return R0
        spacing = 2 * math.pi / so3_grid_size(level)[1]
        return self._refine(R0, steps, lr if lr is not None else spacing / 10)

    def _refine(self, R0: torch.Tensor, steps: int, lr: float) -> torch.Tensor:
        if steps == 0:  # nothing to do (and the learning-rate schedule divides by steps)
            return R0
        # Gradient ascent needs autograd even when called under torch.inference_mode (Lightning's
        # test loop): leave it, and copy the inputs out of inference tensors.
        with torch.inference_mode(False):
            return self._refine_impl(R0.clone(), steps, lr)

    def _refine_impl(self, R0: torch.Tensor, steps: int, lr: float) -> torch.Tensor:
        # All bands at once, as block-diagonal matrices [B, n, n] with n = (lmax+1)^2: one matrix
        # exponential per step instead of one per l (many tiny ops are slow on busy CPUs).
        coeffs = self.coeffs.detach().clone()
        with torch.no_grad():
            angles = matrix_to_angles(R0)
            n = (self.lmax + 1) ** 2
            D0 = coeffs.new_zeros(len(R0), n, n)  # D^l(R0) on the diagonal blocks
            C = torch.zeros_like(D0)  # sqrt(2l+1) c^l on the diagonal blocks
            X = coeffs.new_zeros(3, n, n)  # generators of every band
            for l, block in so3_blocks(self.lmax):
                d, s = 2 * l + 1, l * l
                D0[:, s : s + d, s : s + d] = wigner_D(l, *angles)
                C[:, s : s + d, s : s + d] = coeffs[:, block].reshape(-1, d, d) * math.sqrt(d)
                with default_dtype(torch.float64):  # e3nn builds generators in the default dtype
                    X[:, s : s + d, s : s + d] = o3.so3_generators(l).to(coeffs)
        w = torch.zeros(R0.shape[0], 3, dtype=coeffs.dtype, device=coeffs.device, requires_grad=True)
        optimizer = torch.optim.Adam([w], lr=lr)
        schedule = torch.optim.lr_scheduler.LambdaLR(optimizer, lambda k: 1 - k / steps)
        with torch.enable_grad():
            for _ in range(steps):
                optimizer.zero_grad()
                D = D0 @ torch.linalg.matrix_exp(torch.einsum("bi,ijk->bjk", w, X))  # D(R0 exp(w))  [B, n, n]
                (-(C * D).sum()).backward()
                optimizer.step()
                schedule.step()
        return (R0 @ rotvec_to_matrix(w.detach())).detach()

    def points_above(
        self, threshold: float | torch.Tensor, level: int, max_points: int = 2_000_000
    ) -> list[tuple[torch.Tensor, torch.Tensor]]:
        """Grid points whose probability ``p_i`` is at least ``threshold`` (a number, or one per
        distribution ``(B,)``), per distribution, streamed.

        A point's probability is at most its pixel's gamma-marginal, so only the fibres of pixels
        whose marginal reaches ``threshold`` are evaluated. Returns, for each distribution, ``(index
        (K,), prob (K,))`` in decreasing probability (pixel-major grid indices of ``level``). Raises
        ``ValueError`` when more than ``max_points`` points pass (raise the threshold). A threshold
        must be a probability in ``(0, 1]``; when no point reaches it the entry is empty.
        """
        thresholds = self._thresholds(threshold)
        ev = self._evaluator(level)
        out = []
        with torch.no_grad():
            coeffs = self.coeffs.detach()
            pix_lse = ev.pixel_logsumexp(coeffs)  # [B, P]
            log_z = torch.logsumexp(pix_lse, dim=1)  # [B]
            for b in range(self.batch_size):
                t = float(thresholds[b])
                log_t = math.log(t)
                pix = torch.nonzero(pix_lse[b] - log_z[b] >= log_t).flatten()  # candidate pixels
                if len(pix) * ev.n_gamma > 4 * max_points:
                    raise ConfigError(
                        f"threshold {t:g} keeps too many points at level {level}; raise it (the uniform "
                        f"probability is {1 / ev.n_points:.3g})"
                    )
                log_p = ev.gamma_logits(coeffs[b : b + 1], pix[None])[0] - log_z[b]  # [K, G]
                keep = log_p >= log_t
                index = (pix[:, None] * ev.n_gamma + torch.arange(ev.n_gamma, device=pix.device))[keep]
                prob = log_p[keep].exp()
                if len(index) > max_points:
                    raise ConfigError(f"{len(index)} points pass threshold {t:g} (> max_points={max_points})")
                order = torch.argsort(prob, descending=True)
                out.append((index[order], prob[order]))
        return out

    def _refine_modes(self, b: int, centres: torch.Tensor, level: int) -> torch.Tensor:
        sub = SO3Distribution(self.coeffs[b : b + 1].expand(len(centres), -1), self.lmax)
        spacing = 2 * math.pi / so3_grid_size(level)[1]
        return sub._refine(centres, 100, spacing / 10)

    def sample(
        self, n: int, level: int, generator: torch.Generator | None = None, return_index: bool = False
    ) -> torch.Tensor | tuple[torch.Tensor, torch.Tensor]:
        """``n`` grid rotations per distribution, ``(B, n, 3, 3)``, drawn from the grid softmax.

        Exact and streamed: a pixel is drawn from the gamma-marginal, then gamma given the pixel.
        With ``return_index`` also the flat grid indices ``(B, n)``.
        """
        check_int("n", n, 1)
        ev = self._evaluator(level)
        with torch.no_grad():
            coeffs = self.coeffs.detach()
            pix_logits = ev.pixel_logsumexp(coeffs)  # [B, P]
            pix = torch.multinomial(torch.softmax(pix_logits, -1), n, replacement=True, generator=generator)
            gamma_logits = ev.gamma_logits(coeffs, pix)  # [B, n, G]
            probs = torch.softmax(gamma_logits, -1).reshape(-1, ev.n_gamma)
            k = torch.multinomial(probs, 1, generator=generator).reshape(pix.shape)
            index = pix * ev.n_gamma + k  # [B, n]
        rotations = so3_healpix_index_to_matrix(index, level, dtype=self.coeffs.dtype)
        return (rotations, index) if return_index else rotations
