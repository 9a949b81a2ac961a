"""The Rotation Laplace distribution on SO(3) (Yin, Wang, Chen et al., ICLR 2023, "A Laplace-inspired
distribution on SO(3) for probabilistic rotation estimation").

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; parameter ``A (B, 3, 3)``.
* Proper SVD ``A = U diag(s) V^T`` (``det U = det V = +1``, ``s1 >= s2 >= |s3|``, ``s3 < 0`` iff
  ``det A < 0``; :func:`~image2sphere.so3.rotations.proper_svd`). With
  ``t(R) = tr(diag(s)) - tr(A^T R) >= 0`` (zero only at the mode ``U V^T``), the paper's density
  (its Eq. 3) is

      p(R) = exp(-sqrt(t(R))) / sqrt(t(R)) / c(A),

  here w.r.t. the Haar measure of total volume ``pi^2`` (:mod:`image2sphere.distributions.base`).
  The density is infinite at the mode (integrably); :meth:`RotationLaplace.unnormalized_log_density`
  floors ``t`` at ``T_FLOOR_EPS * (1 + s1 + s2 + s3)`` times the dtype's machine epsilon (the rounding
  scale of ``t``).
* ``c(A)`` is finite unless two of ``c = 2 (s2 + s3, s1 + s3, s1 + s2)`` vanish (``s1 = s2 = -s3``,
  e.g. ``A = -k I``): then the density is singular on a surface and not normalisable.

The normaliser
--------------
The paper approximates ``c(A)`` by a sum over an equivolumetric grid of SO(3); a grid sum of a
density that is infinite at the mode is inaccurate for concentrated distributions, so here it is
computed by quadrature instead. With the Laplace-transform identity (a Gaussian scale mixture)

    exp(-sqrt(t)) / sqrt(t) = pi^(-1/2) int_0^inf lam^(-1/2) exp(-1/(4 lam)) exp(-lam t) dlam,

and ``E_mu exp(-lam t(R)) = c1hat(lam s)`` (the scaled matrix Fisher normaliser of
:func:`~image2sphere.distributions.matrix_fisher.log_scaled_fisher_normalizer`, a 1D Bessel
integral; ``mu`` the Haar probability measure), substituting ``lam = exp(x)``:

    c(A) = pi^2 * pi^(-1/2) int exp(x/2 - exp(-x)/4) c1hat(exp(x) s) dx.

The ``x`` integral is a trapezoid rule with ``LAMBDA_NODES`` nodes on ``[-5, 36 + max(-5, -log c_y)]``
(``c_y = 2 (s1 + s3)``, the middle of ``c``): the integrand is analytic in a strip of half-width
``~pi/2`` and decays double-exponentially to the left and at least like ``exp(-x/2)`` to the right,
so the rule converges exponentially. Measured errors of ``log c``: below ``1e-7`` against an
independent 2D quadrature (over the rotation axis, with an adaptive 1D inner integral) for
``s <= 300``, and below ``1e-6`` up to ``s ~ 1e8`` and for nearly degenerate ``s`` (against finer
rules); the tests also check the Gaussian limit ``c(A) -> pi^2 * 4 / (pi sqrt(c_x c_y c_z))``.
The whole is computed in log space in float64 and differentiable w.r.t. ``A``. ``A = 0`` is
degenerate (``t = 0`` everywhere): the floored density and the truncated ``x`` range give a finite,
meaningless NLL with finite gradients there.

Sampling: by the same identity the distribution is a scale mixture of matrix Fisher distributions
``MF(lam A)`` with mixing density (in ``x = log lam``) proportional to the integrand above.
:meth:`RotationLaplace.exact_sample` draws ``x`` from a piecewise-constant approximation of the mixing
density on ``SAMPLE_NODES`` cells of width ``h ~ 0.08`` (``<= 0.13``): the mixing density is
smooth in ``x``, so the error of this approximation is of order ``h^2/24 < 1e-3`` (relative);
then a matrix Fisher draw (exact Bingham rejection sampling).
"""

from __future__ import annotations

import math

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution
from image2sphere.distributions.matrix_fisher import (
    LOG_HAAR_VOLUME,
    check_parameter_matrix,
    log_scaled_fisher_normalizer,
    sample_bingham_diag,
    work_dtype,
)
from image2sphere.so3.rotations import proper_singular_values, proper_svd, quaternion_to_matrix

__all__ = ["RotationLaplace", "rotation_laplace_log_normalizer", "rotation_laplace_nll"]

LAMBDA_NODES = 96
SAMPLE_NODES = 512
X_LOW = -5.0  # exp(x/2 - exp(-x)/4) < 1e-17 below
X_SPAN_RIGHT = 36.0
X_HIGH_MAX = 60.0
T_FLOOR_EPS = 4.0


def _mixture_terms(s: torch.Tensor, nodes: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Log trapezoid terms ``(B, J)`` of the mixture integral (without ``pi^(-1/2)``) and the nodes
    ``x (B, J)`` for proper singular values ``s (B, 3)``."""
    c_y = (2 * (s[:, 0] + s[:, 2])).detach().clamp_min(1e-30)  # [B]
    x_high = (torch.clamp(-torch.log(c_y), min=X_LOW) + X_SPAN_RIGHT).clamp(max=X_HIGH_MAX)  # [B]
    frac = torch.linspace(0, 1, nodes, dtype=s.dtype, device=s.device)  # [J]
    x = X_LOW + (x_high - X_LOW)[:, None] * frac  # [B, J]
    h = (x_high - X_LOW) / (nodes - 1)  # [B]
    log_weight = torch.log(h)[:, None] + torch.zeros_like(x)
    log_weight[:, [0, -1]] -= math.log(2)
    lam = torch.exp(x)  # [B, J]
    log_c1hat = log_scaled_fisher_normalizer(lam[..., None] * s[:, None, :])  # [B, J, 3] -> [B, J]
    return log_weight + x / 2 - torch.exp(-x) / 4 + log_c1hat, x


def rotation_laplace_log_normalizer(s: torch.Tensor) -> torch.Tensor:
    """``log c`` ``(B,)`` w.r.t. the Haar measure of volume ``pi^2`` for proper singular values
    ``s (B, 3)`` (module docstring), in ``s``'s dtype; differentiable."""
    if s.ndim != 2 or s.shape[-1] != 3:
        raise ConfigError(f"proper singular values must have shape (B, 3), got {tuple(s.shape)}")
    terms, _ = _mixture_terms(s, LAMBDA_NODES)
    return torch.logsumexp(terms, dim=-1) - 0.5 * math.log(math.pi) + LOG_HAAR_VOLUME


def _t_floor(s_sum: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    return (T_FLOOR_EPS * torch.finfo(dtype).eps * (1 + s_sum.detach().abs())).to(dtype)


def _laplace_log_kernel(A: torch.Tensor, s_sum: torch.Tensor, trace: torch.Tensor) -> torch.Tensor:
    """``-sqrt(t) - log(t)/2`` with ``t = s_sum - trace`` floored; ``s_sum (B, 1)``, ``trace (B, K)``."""
    t = torch.maximum(s_sum - trace, _t_floor(s_sum, A.dtype))  # [B, K]
    return -torch.sqrt(t) - 0.5 * torch.log(t)


class RotationLaplace(PoseDistribution):
    """A batch of Rotation Laplace distributions with parameter ``A (B, 3, 3)`` (module docstring)."""

    def __init__(self, A: torch.Tensor):
        self.A = check_parameter_matrix(A, "A")
        self.batch_size, self.dtype, self.device = A.shape[0], A.dtype, A.device

    def _s_sum(self) -> torch.Tensor:
        """``s1 + s2 + s3`` ``(B,)``, differentiable."""
        return proper_singular_values(self.A.to(work_dtype(self.device))).sum(-1).to(self.dtype)

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """``-sqrt(t) - log(t)/2`` at ``(K, 3, 3)`` or ``(B, K, 3, 3)`` rotations: ``(B, K)``."""
        rotations = rotations.to(self.dtype)
        if rotations.ndim == 3:
            trace = torch.einsum("bij,kij->bk", self.A, rotations)  # [B, 3, 3] x [K, 3, 3] -> [B, K]
        elif rotations.ndim == 4 and rotations.shape[0] == self.batch_size:
            trace = torch.einsum("bij,bkij->bk", self.A, rotations)  # [B, 3, 3] x [B, K, 3, 3] -> [B, K]
        else:
            raise ConfigError(
                f"rotations must have shape (K, 3, 3) or (B={self.batch_size}, K, 3, 3), got {tuple(rotations.shape)}"
            )
        return _laplace_log_kernel(self.A, self._s_sum()[:, None], trace)

    def exact_log_normalizer(self) -> torch.Tensor:
        """``log c(A)`` ``(B,)`` by quadrature (module docstring); differentiable."""
        s = proper_singular_values(self.A.to(work_dtype(self.device)))
        return rotation_laplace_log_normalizer(s).to(self.dtype)

    def exact_mode(self) -> torch.Tensor:
        """``U V^T`` from the proper SVD of ``A``: ``(B, 3, 3)``."""
        U, _, V = proper_svd(self.A.detach().to(work_dtype(self.device)))
        return (U @ V.transpose(-1, -2)).to(self.dtype)

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` draws ``(B, n, 3, 3)`` via the matrix Fisher scale mixture (module docstring)."""
        check_int("n", n, 1)
        with torch.no_grad():
            U, s, V = proper_svd(self.A.detach().to(work_dtype(self.device)))
            terms, x = _mixture_terms(s, SAMPLE_NODES)  # [B, J]
            h = x[:, 1] - x[:, 0]  # [B]
            cell = torch.multinomial(torch.softmax(terms, dim=-1), n, replacement=True, generator=generator)
            u = torch.rand(self.batch_size, n, generator=generator, dtype=s.dtype, device=s.device) - 0.5
            lam = torch.exp(torch.gather(x, 1, cell) + u * h[:, None])  # [B, n]
            c = 2 * torch.stack([s[:, 1] + s[:, 2], s[:, 0] + s[:, 2], s[:, 0] + s[:, 1]], dim=-1).clamp_min(0)
            q = sample_bingham_diag((lam[..., None] * c[:, None]).reshape(-1, 3), 1, generator)  # [B n, 1, 4]
            R0 = quaternion_to_matrix(q.reshape(self.batch_size, n, 4), order="wxyz")  # draws of U^T R V
            R = U[:, None] @ R0 @ V.transpose(-1, -2)[:, None]
        return R.to(self.dtype)


def rotation_laplace_nll(A: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    """The training loss of Yin et al.: ``-log p(R | A) = log c(A) + sqrt(t) + log(t)/2``, ``(B,)``,
    for ``A (B, 3, 3)`` and ground truth ``R (B, 3, 3)`` (density w.r.t. the Haar measure of volume
    ``pi^2``)."""
    check_parameter_matrix(A, "A")
    if not isinstance(R, torch.Tensor) or R.shape != A.shape:
        raise ConfigError(f"R must have the shape of A {tuple(A.shape)}, got {tuple(getattr(R, 'shape', ()))}")
    dist = RotationLaplace(A)
    trace = torch.einsum("bij,bij->b", A, R.to(A.dtype))[:, None]  # [B, 3, 3] x [B, 3, 3] -> [B, 1]
    return dist.exact_log_normalizer() - _laplace_log_kernel(A, dist._s_sum()[:, None], trace)[:, 0]
