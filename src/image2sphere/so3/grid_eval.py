"""Evaluation of SO(3) Fourier signals on the HEALPix SO(3) grid without a dense Wigner matrix.

Conventions: flat Wigner layout (:mod:`image2sphere.so3.wigner`), pixel-major grid order
(:mod:`image2sphere.so3.grid`): flat index ``p * n_gamma + k``.

Method
------
On the grid, ``D^l(alpha, beta, gamma) = A^l(alpha, beta) @ Ry^l(gamma)`` with
``A^l = D^l(alpha, beta, 0)``. In e3nn's real basis ``Ry^l(gamma)`` only has the entries
``Ry[n, n] = cos((n - l) gamma)`` and ``Ry[2l - n, n] = sin((n - l) gamma)`` (indices ``0..2l``).
So a coefficient ``c^l[m, n]`` contributes

    c^l[m, n] * sqrt(2l+1) * (A[m, n] cos(t gamma) + sign(n - l) A[m, 2l - n] sin(t gamma)),  t = |n - l|

and on each pixel the signal is a trigonometric polynomial of degree lmax in gamma:

    f(p, gamma) = a_0(p) + sum_{t=1..lmax} a_t(p) cos(t gamma) + b_t(p) sin(t gamma).

Stage 1: for each frequency t, one GEMM ``c[:, I_t] @ W_t`` gives ``(a_t, b_t)`` on all pixels
(``I_t``: the coefficients with ``|n - l| = t``; ``W_t``: their weights per pixel).
Stage 2: one matmul with the ``(2 lmax + 1, n_gamma)`` trigonometric basis gives every gamma.

The operator holds ``(2 n_coeffs - (lmax+1)^2) * n_pixels`` numbers: 861 per pixel for lmax 6,
i.e. ``861 / (455 * n_gamma)`` of the dense matrix (1/101 at level 5). Reductions that need one
number per image stream stage 2 over pixel chunks: besides the operator they hold only the
per-pixel coefficients, ``(2 lmax + 1) / n_gamma`` of the full output (164 MB for a batch of 64
at level 6, whose full output would be 4.8 GB).

Mixed precision (:mod:`image2sphere.precision`): the evaluators are cached per process, so they are
always built with autocast off (in the dtype asked for); they are evaluated in float32 under autocast
whenever a network's ``loss`` or a distribution's method calls them (the only callers in training).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Callable

import torch

from image2sphere.batch_progress import report as report_progress
from image2sphere.checks import ConfigError
from image2sphere.precision import constant_cache
from image2sphere.so3.grid import (
    MAX_DENSE_LEVEL,
    MAX_STREAMED_LEVEL,
    check_level,
    s2_healpix_grid,
    so3_grid_size,
    so3_healpix_grid_angles,
)
from image2sphere.so3.wigner import (
    check_lmax,
    flat_wigner_from_angles,
    n_s2_coeffs,
    n_so3_coeffs,
    so3_blocks,
    so3_layout,
    wigner_D,
)

_log = logging.getLogger(__name__)

__all__ = [
    "MAX_OPERATOR_BYTES",
    "MAX_OUTPUT_BYTES",
    "HealpixGridEvaluator",
    "check_streamed_level",
    "dense_grid_logits",
    "exp_floor",
    "get_grid_evaluator",
]

MAX_OPERATOR_BYTES = 4 * 2**30  # refuse to build operators larger than this
MAX_OUTPUT_BYTES = 4 * 2**30  # refuse to materialise full-grid outputs larger than this
_BUILD_PIXELS = 4096  # pixels per e3nn wigner_D call while building an operator
_CHUNK_ELEMENTS = 2**19  # values of one streamed [batch, pixels, gammas] block (2 MiB float32: cache-sized)
_VISIT_ALIGN = 8  # pixels per chunk handed to a visitor: a multiple of this (HdrMassAccumulator.GROUP_PIXELS)


def exp_floor(dtype: torch.dtype) -> float:
    """The most negative argument whose ``exp`` is a normal number of ``dtype`` (-87 in float32): ``exp``
    of anything lower is below 1e-38 (1e-307 in float64), and producing subnormals is slow on CPUs."""
    return math.log(torch.finfo(dtype).tiny) + 1.0


def _operator_numel(lmax: int, n_pix: int) -> int:
    return (2 * n_so3_coeffs(lmax) - n_s2_coeffs(lmax)) * n_pix


def check_streamed_level(level, name: str = "level") -> int:
    """:func:`~image2sphere.so3.grid.check_level` for streamed evaluation: levels ``0..MAX_STREAMED_LEVEL``."""
    return check_level(level, name, max_level=MAX_STREAMED_LEVEL, purpose="streamed evaluation", bytes_per_point=4)


class HealpixGridEvaluator:
    """Evaluates batches of SO(3) signals (flat Wigner layout) on the level-``level`` HEALPix grid.

    Build it with :func:`get_grid_evaluator` (cached per lmax, level, dtype, device). All methods
    take ``coeffs`` of shape ``(B, n_so3_coeffs(lmax))`` and are differentiable. Levels up to
    :data:`~image2sphere.so3.grid.MAX_STREAMED_LEVEL`; the level and the operator size are checked
    before anything is built.
    """

    def __init__(
        self,
        lmax: int,
        level: int,
        dtype: torch.dtype = torch.float32,
        device: torch.device | str = "cpu",
        max_operator_bytes: int = MAX_OPERATOR_BYTES,
    ):
        self.lmax = check_lmax(lmax)
        self.level = check_streamed_level(level)
        self.n_pix, self.n_gamma = so3_grid_size(level)
        self.n_points = self.n_pix * self.n_gamma
        self.dtype, self.device = dtype, _normalize_device(device)
        nbytes = _operator_numel(lmax, self.n_pix) * torch.finfo(dtype).bits // 8
        if nbytes > max_operator_bytes:
            raise ConfigError(
                f"the grid operator for lmax={lmax}, level={level} needs {nbytes / 2**30:.1f} GiB, more than "
                f"max_operator_bytes={max_operator_bytes / 2**30:.1f} GiB; use a lower grid level"
            )
        alpha, beta = s2_healpix_grid(level, dtype=torch.float64)  # [P]
        l_of, m_of, n_of = so3_layout(lmax)
        freq = (n_of - l_of).abs()  # [n_coeffs]
        # I_t: the coefficients of frequency t, in flat order; W_t: their (cos, sin) weights on every
        # pixel, [n_t, P, 1 or 2], written band by band in the target dtype (no full float64 copy).
        self._index = [torch.nonzero(freq == t).squeeze(1) for t in range(lmax + 1)]
        self._weights = [
            torch.empty(len(idx), self.n_pix, 1 if t == 0 else 2, dtype=dtype) for t, idx in enumerate(self._index)
        ]
        filled = [0] * (lmax + 1)  # rows of W_t written so far
        for l, block in so3_blocks(lmax):
            m, n, f = m_of[block], n_of[block], freq[block]
            for p0 in range(0, self.n_pix, _BUILD_PIXELS):  # blocks bound e3nn's matrix_exp temporaries
                px = slice(p0, p0 + _BUILD_PIXELS)
                A = math.sqrt(2 * l + 1) * wigner_D(l, alpha[px], beta[px], torch.zeros_like(alpha[px]))  # [p, d, d]
                row = list(filled)
                for t in range(l + 1):
                    sel = f == t  # this band's coefficients of frequency t, in flat order
                    rows = slice(row[t], row[t] + int(sel.sum()))
                    self._weights[t][rows, px, 0] = A[:, m[sel], n[sel]].T
                    if t > 0:
                        sign = torch.sign(n[sel] - l).to(A.dtype)[:, None]
                        self._weights[t][rows, px, 1] = sign * A[:, m[sel], 2 * l - n[sel]].T
                    row[t] = rows.stop
            filled = row
        self._index = [idx.to(self.device) for idx in self._index]
        self._weights = [W.to(self.device) for W in self._weights]
        gamma = torch.arange(self.n_gamma, dtype=torch.float64) * (2 * math.pi / self.n_gamma)
        rows = [torch.ones_like(gamma)]
        for t in range(1, lmax + 1):
            rows += [torch.cos(t * gamma), torch.sin(t * gamma)]
        self._basis = torch.stack(rows).to(device=self.device, dtype=dtype)  # [2L+1, G]

    @property
    def operator_bytes(self) -> int:
        tensors = [*self._weights, self._basis]
        return sum(t.numel() * t.element_size() for t in tensors)

    # ------------------------------------------------------------------ helpers
    def _check(self, coeffs: torch.Tensor) -> torch.Tensor:
        n = n_so3_coeffs(self.lmax)
        if coeffs.ndim != 2 or coeffs.shape[1] != n:
            raise ConfigError(f"coeffs must have shape (batch, {n}) for lmax={self.lmax}, got {tuple(coeffs.shape)}")
        if coeffs.dtype != self.dtype or coeffs.device != self.device:
            raise ConfigError(
                f"coeffs are {coeffs.dtype} on {coeffs.device} but this evaluator is {self.dtype} on "
                f"{self.device}; use get_grid_evaluator(lmax, level, dtype, device)"
            )
        return coeffs

    def _gathered(self, coeffs: torch.Tensor) -> list[torch.Tensor]:
        return [coeffs[:, idx] for idx in self._index]  # [B, n_t] each

    def _trig(self, gathered: list[torch.Tensor], p0: int, p1: int) -> torch.Tensor:
        """Trigonometric coefficients ``(a_0, a_1, b_1, ..., a_L, b_L)`` on pixels ``p0:p1``: ``[B, Pc, 2L+1]``."""
        B, Pc = gathered[0].shape[0], p1 - p0
        T = gathered[0].new_empty(B, Pc, 2 * self.lmax + 1)
        for t, (c_t, W) in enumerate(zip(gathered, self._weights, strict=True)):
            W = W[:, p0:p1]  # [n_t, Pc, k]
            out = c_t @ W.reshape(W.shape[0], -1)  # [B, Pc * k]
            if t == 0:
                T[:, :, 0] = out
            else:
                T[:, :, 2 * t - 1 : 2 * t + 1] = out.view(B, Pc, 2)
        return T

    def _pixel_reductions(
        self,
        coeffs: torch.Tensor,
        chunk_pixels: int | None,
        visit: Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int, torch.Tensor], None] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """Max and logsumexp over the gamma fibre of every pixel: two ``[B, P]`` tensors, streamed.

        Stage 1 runs once for all pixels (``[B, P, 2L+1]``, a fraction ``(2L+1) / n_gamma`` of the
        grid); stage 2 and the reductions run on pixel chunks of about ``_CHUNK_ELEMENTS`` values.
        Without autograd each chunk is written into one reused buffer and reduced in place, so
        nothing of chunk size is allocated per chunk and the process's memory stays flat.

        ``visit(values, weights, reference, p0, floor)``, when given, is called once per chunk with its
        values ``[B, Pc, G]`` (pixels ``p0 .. p0 + Pc - 1``, ``Pc`` a multiple of 8 but in the last chunk),
        ``weights = exp(values - reference)`` and ``reference [B]``, the chunk's maximum per signal, which
        the reduction computes on the way (the values stay in place and the exponentials go to a second
        buffer), and ``floor [B]``, a lower bound of the grid's logsumexp (``log G`` plus the largest
        mean of a fibre). It must not keep the tensors: the buffers are reused. With a ``visit`` the pixel
        logsumexps are taken relative to the chunk's maximum, and a value more than ~86 (float32) below it
        counts as exactly that far below (``e^-86``, not a slow subnormal): negligible for the grid's
        logsumexp, the only use of this pass.
        """
        B, G = coeffs.shape[0], self.n_gamma
        step = chunk_pixels or max(1, _CHUNK_ELEMENTS // max(1, B * G))
        step = min(step, self.n_pix)
        if visit is not None and step > _VISIT_ALIGN:  # whole groups of pixels for the visitor
            step -= step % _VISIT_ALIGN
        T = self._trig(self._gathered(coeffs), 0, self.n_pix)  # [B, P, 2L+1]
        if visit is not None:
            # a lower bound of the grid's logsumexp before the sweep: a fibre's logsumexp is at least
            # log(G) plus its mean, a_0
            floor = T[:, :, 0].detach().amax(dim=1) + math.log(G)  # [B]
        reuse = not (torch.is_grad_enabled() and coeffs.requires_grad)
        if reuse:
            buffer = coeffs.new_empty(B * step * G)
            spare = coeffs.new_empty(B * step * G) if visit is not None else None
            pix_max, pix_lse = coeffs.new_empty(B, self.n_pix), coeffs.new_empty(B, self.n_pix)
        else:
            maxes, lses = [], []
        chunks = -(-self.n_pix // step)
        for p0 in range(0, self.n_pix, step):
            report_progress(p0 // step, chunks, f"grid {self.level}", "chunks")  # a long test batch moves
            p1 = min(self.n_pix, p0 + step)
            if reuse:
                x = buffer[: B * (p1 - p0) * G].view(B, p1 - p0, G)
                torch.matmul(T[:, p0:p1], self._basis, out=x)  # [B, Pc, G]
                if visit is None:
                    m = x.amax(dim=2, keepdim=True)  # [B, Pc, 1], finite: the signal is a polynomial
                    pix_max[:, p0:p1] = m.squeeze(2)
                    pix_lse[:, p0:p1] = m.squeeze(2) + x.sub_(m).exp_().sum(dim=2).log()
                    continue
                m = x.amax(dim=2, keepdim=True)  # [B, Pc, 1]
                reference = m.amax(dim=1, keepdim=True)  # [B, 1, 1]: the chunk's maximum
                e = torch.sub(x, reference, out=spare[: x.numel()].view_as(x))  # [B, Pc, G]
                e.clamp_(min=exp_floor(e.dtype)).exp_()  # no subnormal results: they are slow
                pix_max[:, p0:p1] = m.squeeze(2)
                pix_lse[:, p0:p1] = reference.squeeze(2) + e.sum(dim=2).log()
                visit(x, e, reference.reshape(B), p0, floor)
            else:
                x = T[:, p0:p1] @ self._basis  # [B, Pc, G]
                maxes.append(x.amax(dim=2))
                lses.append(torch.logsumexp(x, dim=2))
                if visit is not None:
                    values = x.detach()
                    reference = values.amax(dim=(1, 2))  # [B]
                    visit(values, torch.exp(values - reference[:, None, None]), reference, p0, floor)
        if not reuse:
            pix_max, pix_lse = torch.cat(maxes, dim=1), torch.cat(lses, dim=1)
        return pix_max, pix_lse

    # ------------------------------------------------------------------ full grid
    def logits(self, coeffs: torch.Tensor, max_output_bytes: int = MAX_OUTPUT_BYTES) -> torch.Tensor:
        """Signal on every grid point: ``(B, N)`` in pixel-major order."""
        coeffs = self._check(coeffs)
        B = coeffs.shape[0]
        nbytes = B * self.n_points * coeffs.element_size()
        if nbytes > max_output_bytes:
            raise ConfigError(
                f"full-grid logits for batch {B} at level {self.level} need {nbytes / 2**30:.1f} GiB "
                f"(> max_output_bytes={max_output_bytes / 2**30:.1f} GiB); use the streamed reductions "
                "(logsumexp, max, logits_at) or a smaller batch"
            )
        T = self._trig(self._gathered(coeffs), 0, self.n_pix)  # [B, P, 2L+1]
        return (T @ self._basis).reshape(B, self.n_points)  # [B, P, G] -> [B, N]

    def pixel_logsumexp(self, coeffs: torch.Tensor, chunk_pixels: int | None = None) -> torch.Tensor:
        """``logsumexp`` over the gamma fibre of every pixel: ``(B, P)`` (the S2 marginal, unnormalised)."""
        return self._pixel_reductions(self._check(coeffs), chunk_pixels)[1]

    # ------------------------------------------------------------------ streamed reductions
    def logsumexp_and_max(
        self,
        coeffs: torch.Tensor,
        chunk_pixels: int | None = None,
        visit: Callable[[torch.Tensor, torch.Tensor, torch.Tensor, int, torch.Tensor], None] | None = None,
    ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """One streamed pass: ``(logsumexp (B,), max value (B,), argmax index (B,))`` over the grid.

        ``visit(values, weights, reference, p0, floor)``: called with every chunk of whole gamma fibres
        ``[B, Pc, n_gamma]`` (pixels ``p0 ..``), their ``exp(values - reference)``, ``reference [B]`` and a
        lower bound of the logsumexp ``[B]`` (each grid point once over the pass; see
        :meth:`_pixel_reductions`), e.g.
        :meth:`~image2sphere.distributions.hdr_masses.HdrMassAccumulator.add_fibres`.
        """
        coeffs = self._check(coeffs)
        pix_max, pix_lse = self._pixel_reductions(coeffs, chunk_pixels, visit)
        value, pix = pix_max.max(dim=1)  # [B]
        with torch.no_grad():  # the gamma of the best pixel: one fibre recomputed
            k = self.gamma_logits(coeffs.detach(), pix[:, None])[:, 0].argmax(dim=1)  # [B]
        return torch.logsumexp(pix_lse, dim=1), value, pix * self.n_gamma + k

    def logsumexp(self, coeffs: torch.Tensor, chunk_pixels: int | None = None) -> torch.Tensor:
        """``logsumexp`` of the signal over the grid, ``(B,)``, streamed."""
        return torch.logsumexp(self.pixel_logsumexp(coeffs, chunk_pixels), dim=1)

    def _batched_index(self, index, B: int, upper: int, what: str) -> torch.Tensor:
        """``(K,)`` or ``(B, K)`` integer indices in ``[0, upper)`` -> ``(B, K)`` on this device."""
        index = torch.as_tensor(index, device=self.device)
        if index.ndim == 1:
            index = index[None].expand(B, -1)
        if index.ndim != 2 or index.shape[0] != B or index.is_floating_point() or index.dtype == torch.bool:
            raise ConfigError(
                f"{what} must be integers of shape (K,) or ({B}, K), got {tuple(index.shape)} {index.dtype}"
            )
        if ((index < 0) | (index >= upper)).any():
            raise ConfigError(f"{what} must lie in [0, {upper}) for level {self.level}")
        return index

    def logits_at(self, coeffs: torch.Tensor, index: torch.Tensor) -> torch.Tensor:
        """Signal at grid indices ``index`` ``(B, K)`` (or ``(K,)`` shared by the batch): ``(B, K)``."""
        coeffs = self._check(coeffs)
        index = self._batched_index(index, coeffs.shape[0], self.n_points, "grid indices")
        pix, k = index // self.n_gamma, index % self.n_gamma  # [B, K]
        T = self._trig_at(coeffs, pix)  # [B, K, 2L+1]
        basis = self._basis[:, k].permute(1, 2, 0)  # [B, K, 2L+1]
        return (T * basis).sum(-1)

    def gamma_logits(self, coeffs: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        """Signal on the whole gamma fibre of pixels ``pix`` ``(B, K)`` or ``(K,)``: ``(B, K, n_gamma)``."""
        coeffs = self._check(coeffs)
        pix = self._batched_index(pix, coeffs.shape[0], self.n_pix, "pixel indices")
        return self._trig_at(coeffs, pix) @ self._basis

    def _trig_at(self, coeffs: torch.Tensor, pix: torch.Tensor) -> torch.Tensor:
        B, K = pix.shape
        T = coeffs.new_empty(B, K, 2 * self.lmax + 1)
        for t, (c_t, W) in enumerate(zip(self._gathered(coeffs), self._weights, strict=True)):
            Wp = W[:, pix]  # [n_t, B, K, k]
            out = torch.einsum("bi,ibkc->bkc", c_t, Wp)  # [B, K, k]
            if t == 0:
                T[:, :, 0] = out[..., 0]
            else:
                T[:, :, 2 * t - 1 : 2 * t + 1] = out
        return T


@constant_cache(maxsize=16)  # for training too, whether the first call comes from a test loop or under autocast
def _cached(lmax: int, level: int, dtype: torch.dtype, device: str) -> HealpixGridEvaluator:
    evaluator = HealpixGridEvaluator(lmax, level, dtype=dtype, device=device)
    _log.info("SO(3) grid evaluator built: lmax %d, level %d, %s on %s (process %d)", lmax, level, dtype, device,
              os.getpid())  # fmt: skip
    return evaluator


def get_grid_evaluator(
    lmax: int, level: int, dtype: torch.dtype = torch.float32, device: torch.device | str = "cpu"
) -> HealpixGridEvaluator:
    """The evaluator for ``(lmax, level)`` on ``device`` in ``dtype``, built once per process."""
    lmax, level = check_lmax(lmax), check_streamed_level(level)
    device = _normalize_device(device)
    return _cached(lmax, level, dtype, str(device))


def _normalize_device(device: torch.device | str) -> torch.device:
    """``"cuda"`` -> ``"cuda:<current>"``, so that it compares equal to the device of CUDA tensors."""
    device = torch.device(device)
    if device.type == "cuda" and device.index is None:
        device = torch.device("cuda", torch.cuda.current_device())
    return device


def dense_grid_logits(coeffs: torch.Tensor, lmax: int, level: int, block_points: int = 2**16) -> torch.Tensor:
    """Reference: ``coeffs @ flat_wigner(grid).T`` with the dense Wigner matrix, ``(B, N)``.

    The matrix is built and applied ``block_points`` rows at a time, so memory is the output plus
    one block; the full matrix would be ``N x n_so3_coeffs`` (4.3 GB at level 5). Only for tests
    and benchmarks: it costs ``n_so3_coeffs`` multiply-adds per point and image. Levels up to
    :data:`~image2sphere.so3.grid.MAX_DENSE_LEVEL`.
    """
    lmax = check_lmax(lmax)
    check_level(level, max_level=MAX_DENSE_LEVEL, purpose="dense grid logits", bytes_per_point=4)
    n = n_so3_coeffs(lmax)
    if not isinstance(coeffs, torch.Tensor) or coeffs.ndim != 2 or coeffs.shape[1] != n:
        shape = tuple(coeffs.shape) if isinstance(coeffs, torch.Tensor) else type(coeffs).__name__
        raise ConfigError(f"coeffs must have shape (batch, {n}) for lmax={lmax}, got {shape}")
    nbytes = coeffs.shape[0] * 72 * 8**level * coeffs.element_size()
    if nbytes > MAX_OUTPUT_BYTES:
        raise ConfigError(
            f"dense grid logits for batch {coeffs.shape[0]} at level {level} need {nbytes / 2**30:.1f} GiB "
            f"(> {MAX_OUTPUT_BYTES / 2**30:.1f} GiB); use a smaller batch or level"
        )
    alpha, beta, gamma = so3_healpix_grid_angles(level, dtype=torch.float64)
    out = coeffs.new_empty(coeffs.shape[0], len(alpha))
    for start in range(0, len(alpha), block_points):
        sl = slice(start, start + block_points)
        D = flat_wigner_from_angles(lmax, alpha[sl], beta[sl], gamma[sl])  # [block, n]
        out[:, sl] = coeffs @ D.to(device=coeffs.device, dtype=coeffs.dtype).T
    return out
