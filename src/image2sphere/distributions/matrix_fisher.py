"""The matrix Fisher distribution on SO(3) (Mohlin, Sullivan and Bianchi, NeurIPS 2020).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; parameter ``F (B, 3, 3)``.
* ``p(R) = exp(tr(F^T R)) / c(F)``, a density w.r.t. the Haar measure of total volume ``pi^2`` (the
  project's convention, :mod:`image2sphere.distributions.base`); ``F = 0`` is the uniform density.
* Proper SVD (:func:`~image2sphere.so3.rotations.proper_svd`): ``F = U diag(s) V^T`` with
  ``det U = det V = +1`` and ``s = (s1, s2, s3)``, ``s1 >= s2 >= |s3|``; ``s3 < 0`` exactly when
  ``det F < 0``. The mode is ``U V^T`` (the special-orthogonal polar factor
  ``U' diag(1, 1, det(U' V'^T)) V'^T`` of any SVD ``U' S V'^T``).

The normaliser (the paper's 1D integral, Sec. 3 / Eq. 4, after Wood 1993 and Lee 2018)
--------------------------------------------------------------------------------------
With ``mu`` the Haar *probability* measure, ``c(F) = pi^2 * c1(s)`` where

    c1(s) = int_SO(3) exp(tr(diag(s) R)) dmu(R)
          = int_{-1}^{1} 1/2 I0((s1 - s2)(1 - u)/2) I0((s1 + s2)(1 + u)/2) exp(s3 u) du.

For stability we substitute ``v = 1 - u`` and take out ``exp(s1 + s2 + s3)`` (the integrand's
maximum, reached at ``u = 1`` because ``s2 + s3 >= 0``), writing ``I0(x) = i0e(x) exp(x)``:

    log c1(s) = s1 + s2 + s3 + log int_0^2 1/2 i0e(alpha v) i0e(beta (2 - v)) exp(-gamma v) dv,
    alpha = (s1 - s2)/2,  beta = (s1 + s2)/2,  gamma = s2 + s3   (all >= 0).

The integral (``<= 1``, the "scaled normaliser" ``E_mu exp(-(tr S - tr(S R)))``) is evaluated in
log space (logsumexp) by composite Gauss-Legendre (8 nodes per panel, 272 nodes) on panels that
shrink by factors of 4 towards both ends of ``[0, 2]`` (down to ``4^-16``), where its features
live: ``v ~ 1/alpha``, ``v ~ 1/gamma`` and ``2 - v ~ 1/beta``. Measured errors of ``log c``: below
``1e-7`` against an independent 2D quadrature for ``s <= 300`` and against a finer rule for ``s`` up
to ``1e8``; the tests also check the Gaussian limit ``c1 -> exp(s1 + s2 + s3) / sqrt(pi c_x c_y c_z)``
(``c`` below). Nothing overflows. It is computed in float64 and returned in the parameter's dtype.
Gradients flow through
``torch.linalg.svdvals`` (stable for repeated singular values, e.g. ``F = 0``) and the quadrature;
the derivative of ``i0e`` on ``x >= 0`` is taken as ``i1e(x) - i0e(x)`` also at ``x = 0``.

Sampling (exact): in quaternions ``q = (w, x, y, z)`` (``R = R(q)``),
``tr(diag(s) R(q)) = s1 + s2 + s3 - (c_x x^2 + c_y y^2 + c_z z^2)`` with
``c = 2 (s2 + s3, s1 + s3, s1 + s2) >= 0``, so ``U^T R V`` is the image of a Bingham
distribution on S^3, drawn by rejection from an angular central Gaussian envelope (Kent, Ganeiber
and Mardia 2013, "A new unified approach for the simulation of a wide class of directional
distributions"); the acceptance rate is at least ~28% at any concentration.
"""

from __future__ import annotations

import math

import numpy as np
import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution, check_temperature
from image2sphere.precision import constant_cache
from image2sphere.so3.rotations import proper_singular_values, proper_svd, quaternion_to_matrix

__all__ = [
    "MatrixFisher",
    "check_parameter_matrix",
    "log_scaled_fisher_normalizer",
    "matrix_fisher_nll",
    "sample_bingham_diag",
    "work_dtype",
]

LOG_HAAR_VOLUME = 2 * math.log(math.pi)  # log(pi^2)
# composite Gauss-Legendre on [0, 1]: panels [r^-(k+1), r^-k] (r = PANEL_RATIO) for k < PANELS, then
# [0, r^-PANELS] (4^-16 = 2.3e-10)
PANEL_RATIO = 4
PANELS = 16
NODES_PER_PANEL = 8


def check_parameter_matrix(M: torch.Tensor, name: str) -> torch.Tensor:
    """``ValueError`` unless ``M`` is a finite floating point ``(B, 3, 3)`` tensor."""
    if not isinstance(M, torch.Tensor):
        raise ConfigError(f"{name} must be a tensor of shape (B, 3, 3), got {type(M).__name__}")
    if M.ndim != 3 or M.shape[-2:] != (3, 3) or M.shape[0] < 1:
        raise ConfigError(f"{name} must have shape (B, 3, 3), got {tuple(M.shape)}")
    if not M.is_floating_point():
        raise ConfigError(f"{name} must be a floating point tensor, got {M.dtype}")
    if not torch.isfinite(M).all():
        raise ConfigError(f"{name} of shape {tuple(M.shape)} has non-finite entries")
    return M


def work_dtype(device: torch.device) -> torch.dtype:
    """The dtype of the SVDs and normalisers on ``device``: float64, float32 on ``mps`` (no float64 there)."""
    return torch.float32 if device.type == "mps" else torch.float64


# ---------------------------------------------------------------------------------- the normaliser
class _I0eNonNegative(torch.autograd.Function):
    """``i0e(x)`` for ``x >= 0`` with derivative ``i1e(x) - i0e(x)``, also at ``x = 0``.

    (``torch.special.i0e``'s derivative at 0 uses ``sign(0) = 0``, the average of the two one-sided
    derivatives; on ``x >= 0`` the right derivative ``-1`` is the one that matters.)
    """

    @staticmethod
    def forward(ctx, x):
        value = torch.special.i0e(x)
        ctx.save_for_backward(x, value)
        return value

    @staticmethod
    def backward(ctx, grad):
        x, value = ctx.saved_tensors
        return grad * (torch.special.i1e(x) - value)


@constant_cache(maxsize=8)
def _half_interval_rule(device: torch.device, dtype: torch.dtype) -> tuple[torch.Tensor, torch.Tensor]:
    """Nodes ``(K,)`` and log weights ``(K,)`` of a composite Gauss-Legendre rule on ``[0, 1]``,
    graded geometrically towards 0."""
    x, w = np.polynomial.legendre.leggauss(NODES_PER_PANEL)
    edges = [0.0] + [float(PANEL_RATIO) ** (-k) for k in range(PANELS, -1, -1)]  # 0, 4^-16, ..., 1/4, 1
    nodes, weights = [], []
    for lo, hi in zip(edges[:-1], edges[1:], strict=True):
        nodes.append(lo + (hi - lo) * (x + 1) / 2)
        weights.append(w * (hi - lo) / 2)
    nodes, weights = np.concatenate(nodes), np.concatenate(weights)
    return (torch.as_tensor(nodes, dtype=dtype, device=device),
            torch.as_tensor(np.log(weights), dtype=dtype, device=device))  # fmt: skip


def log_scaled_fisher_normalizer(s: torch.Tensor) -> torch.Tensor:
    """``log E_mu[exp(tr(diag(s) R) - s1 - s2 - s3)]`` (``<= 0``) for proper singular values
    ``s (..., 3)`` (``mu``: Haar probability measure), computed in ``s``'s dtype; differentiable.

    The log normaliser of the matrix Fisher distribution w.r.t. the Haar measure of volume ``pi^2``
    is this plus ``s1 + s2 + s3 + log(pi^2)``. See the module docstring for the formula.
    """
    if s.shape[-1] != 3:
        raise ConfigError(f"proper singular values must have shape (..., 3), got {tuple(s.shape)}")
    t, log_w = _half_interval_rule(s.device, s.dtype)  # [K], [K]: nodes in (0, 1)
    alpha = ((s[..., 0] - s[..., 1]) / 2).clamp_min(0)[..., None]  # [..., 1]
    beta = ((s[..., 0] + s[..., 1]) / 2).clamp_min(0)[..., None]
    gamma = (s[..., 1] + s[..., 2]).clamp_min(0)[..., None]
    parts = []
    # v = t in [0, 1] and v = 2 - t in [1, 2]; 2 - v is then exactly t (no cancellation near v = 2)
    for v, two_minus_v in ((t, 2 - t), (2 - t, t)):
        log_f = (
            torch.log(_I0eNonNegative.apply(alpha * v))
            + torch.log(_I0eNonNegative.apply(beta * two_minus_v))
            - gamma * v
        )  # [..., K]
        parts.append(log_f + log_w)
    return torch.logsumexp(torch.cat(parts, dim=-1), dim=-1) - math.log(2)


def _fisher_log_normalizer(F: torch.Tensor) -> torch.Tensor:
    """Log normaliser ``(B,)`` w.r.t. the Haar measure of volume ``pi^2`` of ``exp(tr(F^T R))``."""
    work = work_dtype(F.device)
    s = proper_singular_values(F.to(work))  # [B, 3]
    log_c = s.sum(-1) + log_scaled_fisher_normalizer(s) + LOG_HAAR_VOLUME
    return log_c.to(F.dtype)


# ---------------------------------------------------------------------------------- Bingham sampling
def _solve_acg_b(c: torch.Tensor) -> torch.Tensor:
    """The root ``b in [1, 4]`` of ``1/b + sum_i 1/(b + 2 c_i) = 1`` for ``c (..., 3) >= 0``: ``(...)``."""
    lo = torch.ones_like(c[..., 0])
    hi = torch.full_like(lo, 4.0)
    for _ in range(60):
        mid = (lo + hi) / 2
        above = 1 / mid + (1 / (mid[..., None] + 2 * c)).sum(-1) > 1  # root is larger than mid
        lo, hi = torch.where(above, mid, lo), torch.where(above, hi, mid)
    return (lo + hi) / 2


def sample_bingham_diag(c: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
    """``n`` exact draws ``(M, n, 4)`` (``wxyz``) from the Bingham densities on S^3
    ``prop. to exp(-(c_x x^2 + c_y y^2 + c_z z^2))`` for ``c (M, 3) >= 0``.

    Rejection from the angular central Gaussian with ``Omega = I + 2 diag(0, c) / b`` (Kent et al.
    2013): with ``z = q^T diag(0, c) q``, ``exp(-z) (q^T Omega q)^2 <= exp(-(4 - b)/2) (4/b)^2``.
    """
    M = c.shape[0]
    work = c.dtype
    c4 = torch.cat([torch.zeros_like(c[:, :1]), c], dim=-1)  # [M, 4]
    b = _solve_acg_b(c)  # [M]
    omega = 1 + 2 * c4 / b[:, None]  # [M, 4]
    log_bound = -(4 - b) / 2 + 2 * torch.log(4 / b)  # [M]
    out = torch.zeros(M, n, 4, dtype=work, device=c.device)
    filled = torch.zeros(M, dtype=torch.long, device=c.device)
    while bool((filled < n).any()):
        m = 4 * n + 16  # acceptance >= ~0.28
        y = torch.randn(M, m, 4, generator=generator, dtype=work, device=c.device) / omega[:, None].sqrt()
        q = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)  # [M, m, 4]
        z = (c4[:, None] * q * q).sum(-1)  # [M, m]
        log_ratio = -z + 2 * torch.log((omega[:, None] * q * q).sum(-1)) - log_bound[:, None]
        u = torch.rand(M, m, generator=generator, dtype=work, device=c.device)
        accept = torch.log(u) < log_ratio  # [M, m]
        slot = filled[:, None] + torch.cumsum(accept.long(), dim=1) - 1  # [M, m]
        keep = accept & (slot < n)
        rows = torch.arange(M, device=c.device)[:, None].expand(M, m)
        out[rows[keep], slot[keep]] = q[keep]
        filled = torch.clamp(filled + accept.long().sum(1), max=n)
    return out


# ---------------------------------------------------------------------------------- the family
class MatrixFisher(PoseDistribution):
    """A batch of matrix Fisher distributions ``p(R) prop. to exp(tr(F^T R))`` with ``F (B, 3, 3)``
    (see the module docstring for the normaliser, the mode and the sampler)."""

    def __init__(self, F: torch.Tensor):
        self.F = check_parameter_matrix(F, "F")
        self.batch_size, self.dtype, self.device = F.shape[0], F.dtype, F.device

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """``tr(F^T R)`` at ``(K, 3, 3)`` or ``(B, K, 3, 3)`` rotations: ``(B, K)``."""
        rotations = rotations.to(self.dtype)
        if rotations.ndim == 3:
            return torch.einsum("bij,kij->bk", self.F, rotations)  # [B, 3, 3] x [K, 3, 3] -> [B, K]
        if rotations.ndim == 4 and rotations.shape[0] == self.batch_size:
            return torch.einsum("bij,bkij->bk", self.F, rotations)  # [B, 3, 3] x [B, K, 3, 3] -> [B, K]
        raise ConfigError(
            f"rotations must have shape (K, 3, 3) or (B={self.batch_size}, K, 3, 3), got {tuple(rotations.shape)}"
        )

    def tempered(self, temperature: float) -> MatrixFisher:
        """``p ** (1 / temperature)``, renormalised: the matrix Fisher family with ``F / temperature``
        (its closed-form normaliser, mode and sampler stay exact)."""
        temperature = check_temperature(temperature)
        return self if temperature == 1.0 else MatrixFisher(self.F / temperature)

    def exact_log_normalizer(self) -> torch.Tensor:
        """``log c(F)`` ``(B,)`` w.r.t. the Haar measure of volume ``pi^2``; differentiable."""
        return _fisher_log_normalizer(self.F)

    def exact_mode(self) -> torch.Tensor:
        """``U V^T`` from the proper SVD of ``F``: ``(B, 3, 3)``."""
        U, _, V = proper_svd(self.F.detach().to(work_dtype(self.device)))
        return (U @ V.transpose(-1, -2)).to(self.dtype)

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)`` (Bingham rejection sampling, module docstring)."""
        check_int("n", n, 1)
        with torch.no_grad():
            U, s, V = proper_svd(self.F.detach().to(work_dtype(self.device)))
            c = 2 * torch.stack([s[:, 1] + s[:, 2], s[:, 0] + s[:, 2], s[:, 0] + s[:, 1]], dim=-1).clamp_min(0)
            q = sample_bingham_diag(c, n, generator)  # [B, n, 4]
            R0 = quaternion_to_matrix(q, order="wxyz")  # [B, n, 3, 3]: draws of U^T R V
            R = U[:, None] @ R0 @ V.transpose(-1, -2)[:, None]
        return R.to(self.dtype)


def matrix_fisher_nll(F: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """The training loss of Mohlin et al.: ``-log p(R | F) = log c(F) - tr(F^T R)``, ``(B,)``, for
    ``F (B, 3, 3)`` and ground truth ``R (B, 3, 3)`` (density w.r.t. the Haar measure of volume
    ``pi^2``: the uniform distribution scores ``log(pi^2) = 2.2894``)."""
    check_parameter_matrix(F, "F")
    if not isinstance(R, torch.Tensor) or R.shape != F.shape:
        raise ConfigError(f"R must have the shape of F {tuple(F.shape)}, got {tuple(getattr(R, 'shape', ()))}")
    R = R.to(F.dtype)
    return _fisher_log_normalizer(F) - torch.einsum("bij,bij->b", F, R)  # [B, 3, 3] x [B, 3, 3] -> [B]
