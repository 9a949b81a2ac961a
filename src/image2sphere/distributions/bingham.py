"""Bingham distributions (and mixtures of them) on unit quaternions, as distributions over SO(3).

Baselines: Gilitschenski et al. 2020, "Deep orientation uncertainty learning based on a Bingham
loss" (one component) and Deng et al. 2022, "Deep Bingham networks" (a mixture).

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; quaternions ``q = (w, x, y, z)`` (scalar
  first, :func:`image2sphere.so3.quaternion_to_matrix` with ``order="wxyz"``), Hamilton product
  (:func:`image2sphere.so3.quaternion_multiply`), so ``R(p * q) = R(p) @ R(q)``. ``q`` and ``-q``
  are the same rotation; the Bingham density is antipodally symmetric, so it is a function of the
  rotation.
* Component ``c`` of distribution ``b``: an orthonormal ``M (4, 4)`` and concentrations
  ``z = (z1, z2, z3)`` with ``z1 <= z2 <= z3 <= 0`` (Gilitschenski's order), ``Z = diag(z1, z2, z3, 0)``,
  ``A = M Z M^T``: ``f(q) ∝ exp(q^T A q)``. The column ``M[:, 3]`` (eigenvalue 0) is the mode.
* **Densities are w.r.t. the Haar measure of volume pi^2.** The double cover ``S^3 -> SO(3)``
  pushes the surface measure of ``S^3`` (area ``2 pi^2``) to twice that Haar measure, so for any
  ``g`` on SO(3), ``int_SO(3) g dR = 1/2 int_S3 g(R(q)) dS(q)``. With ``F(Z) = int_S3 exp(q^T A q) dS``
  (the usual Bingham normaliser) the SO(3) density is ``p(R) = 2 exp(q^T A q) / F(Z)``, i.e. the
  SO(3) log normaliser is ``log F(Z) - log 2`` (``log pi^2`` for ``Z = 0``).
* The mixture ``p(R) = sum_c w_c p_c(R)`` is normalised per component and then weighted, so
  :meth:`Bingham.unnormalized_log_density` is already the normalised log density and
  :meth:`Bingham.exact_log_normalizer` is 0; :meth:`Bingham.component_log_normalizers` gives the
  per-component ``log F(Z_c) - log 2``.

The normaliser
--------------
In Hopf coordinates ``q = (cos th cos f1, cos th sin f1, sin th cos f2, sin th sin f2)``,
``dS = sin th cos th dth df1 df2``; integrating out ``f1, f2`` (``int exp(r (u cos f^2 + v sin f^2)) df
= 2 pi exp(r (u + v) / 2) I0(r (u - v) / 2)``) and substituting ``t = cos^2 th`` gives the exact 1D
integral (pairing ``(z1, z2)`` and ``(z3, 0)``)

    F(Z) = 2 pi^2 int_0^1 exp(z2 t) I0e((z1 - z2) t / 2) I0e(z3 (1 - t) / 2) dt,

(``I0e(x) = exp(-|x|) I0(x)``), whose integrand is at most 1 and whose features all sit at
``t = 0`` on scales ``1 / |z2|`` and ``2 / |z1 - z2|``. It is evaluated in log space (logsumexp)
in float64 by tanh-sinh (double exponential) quadrature with :data:`_DE_NODES` fixed nodes, which
resolves endpoint layers down to ``t ~ 1e-37``: the relative error of ``F`` is below ``1e-10``
(against mpmath) for ``0 >= z >= -1e5`` (see the tests). Gradients are those of the quadrature
sum (finite, accurate to the same order).
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution, check_num_components
from image2sphere.rotation_sets import check_labels
from image2sphere.so3.rotations import (
    check_rotation_matrix,
    matrix_to_quaternion_outer,
    quaternion_multiply,
    quaternion_to_matrix,
)

__all__ = [
    "PARAMS_PER_COMPONENT",
    "Bingham",
    "bingham_log_normalizer",
    "bingham_nll",
    "bingham_params_from_output",
    "quaternion_basis_matrix",
]

#: raw network outputs per mixture component (see :func:`bingham_params_from_output`)
PARAMS_PER_COMPONENT = 8
#: concentration logits are clamped to this range before ``exp`` (|z| <= 3 e^10 ~ 6.6e4)
LOGIT_RANGE = (-10.0, 10.0)
LOG_PI2 = 2 * math.log(math.pi)


def _tanh_sinh_nodes(h: float = 1.0 / 32, s_max: float = 4.0) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """Tanh-sinh rule on ``[0, 1]``: ``(t, 1 - t, log weight)``, each ``(K,)`` float64.

    ``t = sigmoid(pi sinh s)``, ``dt / ds = pi cosh s t (1 - t)``; ``1 - t`` and the log weights are
    computed without cancellation, so nodes reach ``t ~ exp(-pi sinh s_max) ~ 1e-37``.
    """
    s = torch.arange(-s_max, s_max + h / 2, h, dtype=torch.float64)
    u = math.pi * torch.sinh(s)
    log_w = math.log(h) + torch.log(math.pi * torch.cosh(s)) + F.logsigmoid(u) + F.logsigmoid(-u)
    return torch.sigmoid(u), torch.sigmoid(-u), log_w


_DE_T, _DE_1MT, _DE_LOGW = _tanh_sinh_nodes()
_DE_NODES = len(_DE_T)


def bingham_log_normalizer(z: torch.Tensor) -> torch.Tensor:
    """``log F(Z) - log 2`` for ``Z = diag(z1, z2, z3, 0)``: the log normaliser w.r.t. the Haar measure
    of volume ``pi^2`` of ``exp(q^T M Z M^T q)``. ``z (..., 3)``, ascending, ``<= 0``: ``(...)``.

    Computed in float64 (returned in ``z``'s dtype); differentiable. See the module docstring.
    """
    if z.ndim < 1 or z.shape[-1] != 3:
        raise ConfigError(f"z must have shape (..., 3), got {tuple(z.shape)}")
    zd = z.to(torch.float64)
    t, one_minus_t, log_w = (v.to(zd.device) for v in (_DE_T, _DE_1MT, _DE_LOGW))
    z1, z2, z3 = (zd[..., i, None] for i in range(3))  # [..., 1]
    # log of the integrand (<= 0) at the nodes  [..., K]
    log_f = (
        z2 * t + torch.log(torch.special.i0e((z1 - z2) * t / 2)) + torch.log(torch.special.i0e(z3 * one_minus_t / 2))
    )
    log_integral = torch.logsumexp(log_f + log_w, dim=-1)  # [...]
    return (LOG_PI2 + log_integral).to(z.dtype)


# ---------------------------------------------------------------------------------- quaternions
def quaternion_basis_matrix(q: torch.Tensor) -> torch.Tensor:
    """Orthonormal ``M (..., 4, 4)`` with columns ``(q * i, q * j, q * k, q)`` of unit ``q (..., 4)``.

    ``M(q) = L(q) P`` (``L(q)``: left multiplication by ``q``, orthogonal; ``P`` a permutation), so
    ``L(p) M(q) = M(p * q)``: a Bingham built on ``M(q)`` moves with ``q`` under left
    multiplication (``R -> Q R``). The last column (eigenvalue 0 of ``Z``) is ``q`` itself.
    """
    basis = torch.eye(4, dtype=q.dtype, device=q.device)  # rows 1, i, j, k
    cols = [quaternion_multiply(q, basis[i].expand_as(q)) for i in (1, 2, 3, 0)]
    return torch.stack(cols, dim=-1)


# ---------------------------------------------------------------------------------- parameters
def bingham_params_from_output(x: torch.Tensor, num_components: int = 1):
    """Raw network output ``x (B, C * 8)`` -> ``(M (B, C, 4, 4), z (B, C, 3), weights (B, C))``.

    Layout per component ``c`` (component-major: ``x.view(B, C, 8)``):

    * ``[0:4]`` a quaternion ``v`` (wxyz, normalised here): ``M = (v i, v j, v k, v)``
      (:func:`quaternion_basis_matrix`), so ``v`` is the component's mode;
    * ``[4:7]`` concentration logits ``y``: ``z = -cumsum(exp(y))`` reversed, i.e.
      ``z3 = -e^{y0}``, ``z2 = z3 - e^{y1}``, ``z1 = z2 - e^{y2}`` (ascending ``z1 <= z2 <= z3 < 0``,
      Gilitschenski et al.'s parametrisation), ``y`` clamped to :data:`LOGIT_RANGE`;
    * ``[7]`` a mixture logit: ``weights = softmax`` over components (ignored when ``C = 1``).
    """
    M, z, log_w = _params(x, num_components)
    return M, z, log_w.exp()


def _params(x: torch.Tensor, num_components: int):
    C = check_num_components(num_components)
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != C * PARAMS_PER_COMPONENT:
        raise ConfigError(
            f"Bingham output must have shape (B, {C * PARAMS_PER_COMPONENT}) for {C} component(s) "
            f"({PARAMS_PER_COMPONENT} per component), got {tuple(getattr(x, 'shape', ()))}"
        )
    x = x.reshape(x.shape[0], C, PARAMS_PER_COMPONENT)  # [B, C, 8]
    v = x[..., :4]
    v = v / torch.linalg.vector_norm(v, dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny ** 0.5)
    M = quaternion_basis_matrix(v)  # [B, C, 4, 4]
    z = -torch.cumsum(torch.exp(x[..., 4:7].clamp(*LOGIT_RANGE)), dim=-1).flip(-1)  # [B, C, 3] ascending
    log_w = torch.log_softmax(x[..., 7], dim=-1)  # [B, C]
    return M, z, log_w


# ---------------------------------------------------------------------------------- distribution
class Bingham(PoseDistribution):
    """A batch of ``B`` mixtures of ``C >= 1`` Bingham distributions over SO(3).

    ``M (B, C, 4, 4)`` orthonormal, ``z (B, C, 3)`` concentrations ``<= 0`` for the first three
    columns of ``M`` (the fourth has concentration 0: the mode), mixture ``weights (B, C)`` (or
    ``log_weights``; default uniform). See the module docstring for the density and its normaliser.
    """

    def __init__(
        self,
        M: torch.Tensor,
        z: torch.Tensor,
        weights: torch.Tensor | None = None,
        *,
        log_weights: torch.Tensor | None = None,
    ):
        if M.ndim != 4 or M.shape[-2:] != (4, 4):
            raise ConfigError(f"M must have shape (B, C, 4, 4), got {tuple(M.shape)}")
        B, C = M.shape[:2]
        if z.shape != (B, C, 3):
            raise ConfigError(f"z must have shape (B, C, 3) = {(B, C, 3)}, got {tuple(z.shape)}")
        if not M.is_floating_point():
            raise ConfigError(f"M must be a floating point tensor, got {M.dtype}")
        with torch.no_grad():
            eye = torch.eye(4, dtype=torch.float64, device=M.device)
            Md = M.detach().double()
            err = (Md.transpose(-1, -2) @ Md - eye).abs().amax() if M.numel() else 0.0
            if not torch.isfinite(torch.as_tensor(err)) or err > 1e-3:
                raise ConfigError(f"M of shape {tuple(M.shape)} is not orthonormal: max |M^T M - I| = {float(err):.3g}")
            if not torch.isfinite(z).all() or (z > 0).any():
                raise ConfigError(f"z of shape {tuple(z.shape)} must be finite and <= 0")
        if weights is not None and log_weights is not None:
            raise ConfigError("give weights or log_weights, not both")
        if weights is not None:
            if weights.shape != (B, C):
                raise ConfigError(f"weights must have shape (B, C) = {(B, C)}, got {tuple(weights.shape)}")
            log_weights = torch.log(weights.clamp_min(torch.finfo(weights.dtype).tiny))
        if log_weights is None:
            log_weights = torch.full((B, C), -math.log(C), dtype=M.dtype, device=M.device)
        if log_weights.shape != (B, C):
            raise ConfigError(f"log_weights must have shape (B, C) = {(B, C)}, got {tuple(log_weights.shape)}")
        self.M, self.z = M, z.to(M.dtype)
        self.log_weights = log_weights.to(M.dtype)
        self.num_components = C
        self.batch_size, self.dtype, self.device = B, M.dtype, M.device

    @classmethod
    def from_output(cls, x: torch.Tensor, num_components: int = 1) -> Bingham:
        """The distribution of a raw network output ``(B, C * 8)`` (:func:`bingham_params_from_output`)."""
        M, z, log_w = _params(x, num_components)
        return cls(M, z, log_weights=log_w)

    # ------------------------------------------------------------------ the family
    @property
    def weights(self) -> torch.Tensor:
        """Mixture weights ``(B, C)``."""
        return self.log_weights.exp()

    def concentration_matrix(self) -> torch.Tensor:
        """``A = M diag(z1, z2, z3, 0) M^T``: ``(B, C, 4, 4)``."""
        Z = torch.cat([self.z, torch.zeros_like(self.z[..., :1])], dim=-1)  # [B, C, 4]
        return torch.einsum("bcik,bck,bcjk->bcij", self.M, Z, self.M)  # [B, C, 4, 4]

    def component_log_normalizers(self) -> torch.Tensor:
        """``log F(Z_c) - log 2`` per component ``(B, C)`` (Haar measure of volume ``pi^2``)."""
        return bingham_log_normalizer(self.z)

    def component_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """Normalised log density of each component at ``(K, 3, 3)`` or ``(B, K, 3, 3)``: ``(B, C, K)``."""
        qq = matrix_to_quaternion_outer(rotations.to(self.dtype))  # [(B,) K, 4, 4]
        A = self.concentration_matrix()  # [B, C, 4, 4]
        if rotations.ndim == 3:
            quad = torch.einsum("bcij,kij->bck", A, qq)  # q^T A q  [B, C, K]
        else:
            quad = torch.einsum("bcij,bkij->bck", A, qq)  # [B, C, K]
        return quad - self.component_log_normalizers()[..., None]

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """The (already normalised) mixture log density ``log sum_c w_c p_c(R)``: ``(B, K)``."""
        if rotations.ndim not in (3, 4) or rotations.shape[-2:] != (3, 3):
            raise ConfigError(f"rotations must have shape (B, K, 3, 3) or (K, 3, 3), got {tuple(rotations.shape)}")
        return torch.logsumexp(self.component_log_density(rotations) + self.log_weights[..., None], dim=1)

    def exact_log_normalizer(self) -> torch.Tensor:
        """0 ``(B,)``: :meth:`unnormalized_log_density` is already normalised (per component)."""
        return torch.zeros(self.batch_size, dtype=self.dtype, device=self.device)

    def component_modes(self) -> torch.Tensor:
        """The mode of each component, ``(B, C, 3, 3)``: the rotation of ``M[..., :, 3]``."""
        return quaternion_to_matrix(self.M[..., :, 3], order="wxyz")

    def exact_mode(self) -> torch.Tensor:
        """``(B, 3, 3)``: of the component modes, the one where the mixture density is highest (for
        one component, or well separated components of equal shape, the heaviest component's mode;
        exact for ``C = 1``, otherwise the mixture's peak up to the other components' pull)."""
        modes = self.component_modes()  # [B, C, 3, 3]
        if self.num_components == 1:
            return modes[:, 0]
        with torch.no_grad():
            best = self.unnormalized_log_density(modes).argmax(dim=1)  # [B]
        return modes[torch.arange(self.batch_size, device=self.device), best]

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)``: a component per draw from the weights, then rejection
        sampling from an angular central Gaussian envelope (Kent, Ganeiber & Mardia 2013)."""
        check_int("n", n, 1)
        B, dev = self.batch_size, self.device
        with torch.no_grad():
            comp = torch.multinomial(self.weights.double().cpu(), n, replacement=True, generator=generator)  # [B, n]
            comp = comp.to(dev)
            lam = torch.cat([-self.z, torch.zeros_like(self.z[..., :1])], dim=-1).double()  # [B, C, 4] >= 0
            b = _acg_b(lam)  # [B, C]
            idx = torch.arange(B, device=dev)[:, None]
            lam_d, b_d = lam[idx, comp].reshape(B * n, 4), b[idx, comp].reshape(B * n)  # [P, 4], [P]
            x = _sample_bingham_eigenbasis(lam_d, b_d, generator)  # [P, 4]
            M = self.M.double()[idx, comp].reshape(B * n, 4, 4)
            q = torch.einsum("pij,pj->pi", M, x)  # [P, 4]
            return quaternion_to_matrix(q, order="wxyz").reshape(B, n, 3, 3).to(self.dtype)


def _acg_b(lam: torch.Tensor) -> torch.Tensor:
    """Root ``b in [1, 4]`` of ``sum_i 1 / (b + 2 lam_i) = 1`` (``lam (..., 4) >= 0``): ``(...)``."""
    lo = torch.ones(lam.shape[:-1], dtype=lam.dtype, device=lam.device)
    hi = torch.full_like(lo, 4.0)
    for _ in range(60):
        mid = (lo + hi) / 2
        too_small = (1 / (mid[..., None] + 2 * lam)).sum(-1) > 1  # g decreasing in b
        lo, hi = torch.where(too_small, mid, lo), torch.where(too_small, hi, mid)
    return (lo + hi) / 2


def _sample_bingham_eigenbasis(lam: torch.Tensor, b: torch.Tensor, generator) -> torch.Tensor:
    """Draws ``x (P, 4)`` on S^3 with density ∝ ``exp(-sum_i lam_i x_i^2)``, by rejection from the
    ACG with ``Omega = I + 2 diag(lam) / b``: accept when ``log u < -x^T L x + 2 log(x^T Omega x) +
    (4 - b) / 2 - 2 log(4 / b)`` (the bound ``M* = exp(-(q - b) / 2) (q / b)^{q / 2}``, ``q = 4``)."""
    P = lam.shape[0]
    out = torch.empty((P, 4), dtype=lam.dtype, device=lam.device)
    todo = torch.arange(P, device=lam.device)
    while len(todo):
        lt, bt = lam[todo], b[todo, None]  # [p, 4], [p, 1]
        omega = 1 + 2 * lt / bt  # [p, 4]
        y = torch.randn(lt.shape, generator=generator, dtype=lam.dtype, device=lam.device) / omega.sqrt()
        x = y / torch.linalg.vector_norm(y, dim=-1, keepdim=True)
        log_ratio = (
            -(lt * x**2).sum(-1)
            + 2 * torch.log((omega * x**2).sum(-1))
            + (4 - bt[:, 0]) / 2
            - 2 * torch.log(4 / bt[:, 0])
        )
        u = torch.rand(len(todo), generator=generator, dtype=lam.dtype, device=lam.device)
        accept = torch.log(u) < log_ratio
        out[todo[accept]] = x[accept]
        todo = todo[~accept]
    return out


def bingham_nll(dist_or_output: Bingham | torch.Tensor, rotation: torch.Tensor, num_components: int = 1):
    """Negative log likelihood ``(B,)`` of ``rotation (B, 3, 3)`` under a :class:`Bingham` or the
    distribution of a raw output ``(B, C * 8)`` (Haar measure of volume ``pi^2``; mean it for a loss)."""
    dist = dist_or_output
    if not isinstance(dist, Bingham):
        dist = Bingham.from_output(dist_or_output, num_components)
    check_labels(rotation, dist.batch_size)
    check_rotation_matrix(rotation, "rotation", atol=1e-3)
    return -dist.unnormalized_log_density(rotation[:, None].to(dist.dtype))[:, 0]
