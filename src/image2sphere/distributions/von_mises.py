"""Mixtures of von Mises distributions on three Euler angles, as distributions over SO(3).

Baseline: Prokudin, Gehler & Nowozin 2018, "Deep directional statistics: pose estimation with
uncertainty quantification" (finite mixture of products of von Mises on azimuth, elevation and
tilt, means predicted as biternions ``(cos, sin)``).

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``.
* **Euler angles** ``(a, e, t)`` = (azimuth, elevation, tilt), each on a full circle, mapped to a
  rotation as in the PASCAL3D+ viewpoint evaluation that Prokudin et al. use (RenderForCNN's
  ``angle2dcm(r, 'ZYX') = Tx(r3) Ty(r2) Tz(r1)``, ``T`` the passive (transposed) rotations):

      R(a, e, t) = Rx(-t) @ Ry(-e) @ Rz(-a)        (:func:`~image2sphere.so3.rotations.aet_to_matrix`)

  with ``Rx, Ry, Rz`` the active right-handed axis rotations. These are *not* the project's e3nn
  Y-X-Y angles: the chart only fixes what "a von Mises on each angle" means and where its
  singularity lies (elevation ``+-pi/2``, a camera straight above or below the object, which is rare
  in PASCAL3D+; the Y-X-Y chart would put it at ``beta = 0``, around the identity).
* Density of component ``c``: ``f_c(a, e, t) = prod_i exp(k_i cos(x_i - mu_i)) / (2 pi I0(k_i))``
  w.r.t. ``da de dt`` on the torus ``T^3``. Every angle is a full circle, so the von Mises factors
  are proper densities; the map ``T^3 -> SO(3)`` is then 2:1, ``(a, e, t)`` and
  ``(a + pi, pi - e, t + pi)`` giving the same rotation. The Haar measure of volume ``pi^2`` is
  ``|cos e| da de dt / 8`` in these coordinates (``2 pi * 2 * 2 pi / 8 = pi^2`` over one sheet), so
  the pushed-forward density w.r.t. it is (change of variables, summed over both preimages)

      p(R) = sum_c w_c * 8 * (f_c(a, e, t) + f_c(a + pi, pi - e, t + pi)) / |cos e|,

  which integrates to 1 exactly. It is unbounded (integrably, like ``1 / distance``) near the two
  circles ``cos e = 0`` of SO(3), and the HEALPix SO(3) grid has ``8 nside`` points exactly on
  them, so :attr:`VonMisesEuler.jacobian_floor` (default ``1e-2``) caps the Jacobian factor:
  ``|cos e| -> max(|cos e|, floor)``. That removes the mass ``int f (1 - |cos e| / floor)_+``: at
  most ``2 floor g_max`` with ``g_max`` the elevation marginal's density near ``+-pi/2``
  (``<= 0.3%`` for any broad distribution, 0 to double precision when the elevation stays ``3 /
  sqrt(kappa_e)`` away from ``+-pi/2``). ``jacobian_floor=0`` gives the exact pushforward (clamped
  only at the dtype's epsilon).
* The mixture is normalised per component and then weighted, so
  :meth:`VonMisesEuler.unnormalized_log_density` is already normalised and
  :meth:`VonMisesEuler.exact_log_normalizer` is 0. :meth:`VonMisesEuler.component_log_normalizers`
  gives the closed form ``sum_i log(2 pi I0(k_i))`` of the unnormalised ``exp(sum_i k_i cos(x_i -
  mu_i))`` (torus or, with the Jacobian above, SO(3)), evaluated as ``log 2 pi + log i0e(k) + k``:
  stable for any ``k > 0``.
"""

from __future__ import annotations

import math

import torch
import torch.nn.functional as F

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution, check_num_components
from image2sphere.rotation_sets import check_labels
from image2sphere.so3.rotations import (
    aet_biternions_to_matrix,
    aet_to_matrix,
    check_rotation_matrix,
    matrix_to_aet_biternions,
)

__all__ = [
    "JACOBIAN_FLOOR",
    "MIN_CONCENTRATION",
    "PARAMS_PER_COMPONENT",
    "VonMisesEuler",
    "sample_von_mises",
    "von_mises_log_normalizer",
    "von_mises_nll",
    "von_mises_params_from_output",
]

#: raw network outputs per mixture component (see :func:`von_mises_params_from_output`)
PARAMS_PER_COMPONENT = 10
#: added to ``softplus`` of the concentration logits
MIN_CONCENTRATION = 1e-3
#: default cap ``|cos e| -> max(|cos e|, JACOBIAN_FLOOR)`` of the Jacobian (module docstring)
JACOBIAN_FLOOR = 1e-2
LOG_2PI = math.log(2 * math.pi)


def von_mises_log_normalizer(kappa: torch.Tensor) -> torch.Tensor:
    """``log(2 pi I0(kappa)) = log 2 pi + log i0e(kappa) + kappa`` elementwise (stable, ``kappa >= 0``)."""
    return LOG_2PI + torch.log(torch.special.i0e(kappa)) + kappa


# ---------------------------------------------------------------------------------- parameters
def von_mises_params_from_output(x: torch.Tensor, num_components: int = 1):
    """Raw network output ``x (B, C * 10)`` -> ``(mu (B, C, 3, 2), kappa (B, C, 3), weights (B, C))``.

    Layout per component (component-major, ``x.view(B, C, 10)``): ``[0:6]`` three biternions
    ``(cos, sin)`` of the mean azimuth, elevation, tilt (each pair normalised here, Prokudin et al.'s
    BiternionNet head); ``[6:9]`` concentration logits, ``kappa = softplus + MIN_CONCENTRATION``;
    ``[9]`` a mixture logit, ``weights = softmax`` over components (ignored when ``C = 1``).
    """
    mu, kappa, log_w = _params(x, num_components)
    return mu, kappa, log_w.exp()


def _params(x: torch.Tensor, num_components: int):
    C = check_num_components(num_components)
    if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != C * PARAMS_PER_COMPONENT:
        raise ConfigError(
            f"von Mises output must have shape (B, {C * PARAMS_PER_COMPONENT}) for {C} component(s) "
            f"({PARAMS_PER_COMPONENT} per component), got {tuple(getattr(x, 'shape', ()))}"
        )
    x = x.reshape(x.shape[0], C, PARAMS_PER_COMPONENT)  # [B, C, 10]
    mu = x[..., :6].reshape(*x.shape[:2], 3, 2)  # [B, C, 3, 2]
    mu = mu / torch.linalg.vector_norm(mu, dim=-1, keepdim=True).clamp_min(torch.finfo(x.dtype).tiny ** 0.5)
    kappa = F.softplus(x[..., 6:9]) + MIN_CONCENTRATION  # [B, C, 3]
    return mu, kappa, torch.log_softmax(x[..., 9], dim=-1)


# ---------------------------------------------------------------------------------- sampling
def sample_von_mises(mu: torch.Tensor, kappa: torch.Tensor, generator: torch.Generator | None = None) -> torch.Tensor:
    """One von Mises draw per element of ``mu, kappa (...)`` (radians, in ``(-pi, pi]``): ``(...)``.

    Best & Fisher (1979) rejection sampler, float64, with ``rho`` written without cancellation.
    """
    kd = kappa.detach().double().reshape(-1)
    tau = 1 + torch.sqrt(1 + 4 * kd**2)
    rho = 2 * kd * tau / ((torch.sqrt(1 + 4 * kd**2) + 1) * (tau + torch.sqrt(2 * tau)))
    r = (1 + rho**2) / (2 * rho)
    out = torch.empty_like(kd)
    todo = torch.arange(len(kd), device=kd.device)
    while len(todo):
        u1, u2, u3 = torch.rand((3, len(todo)), generator=generator, dtype=kd.dtype, device=kd.device)
        k, rr = kd[todo], r[todo]
        zc = torch.cos(math.pi * u1)
        f = (1 + rr * zc) / (rr + zc)
        c = k * (rr - f)
        accept = (c * (2 - c) - u2 > 0) | (torch.log(c / u2) + 1 - c >= 0)
        theta = torch.sign(u3 - 0.5) * torch.acos(f.clamp(-1, 1))
        out[todo[accept]] = theta[accept]
        todo = todo[~accept]
    angle = out.reshape(kappa.shape) + mu.detach().double()
    return torch.remainder(angle + math.pi, 2 * math.pi) - math.pi


# ---------------------------------------------------------------------------------- distribution
class VonMisesEuler(PoseDistribution):
    """A batch of ``B`` mixtures of ``C >= 1`` products of von Mises on (azimuth, elevation, tilt).

    ``mu (B, C, 3, 2)`` mean biternions ``(cos, sin)`` (normalised here), ``kappa (B, C, 3) > 0``,
    mixture ``weights (B, C)`` (or ``log_weights``; default uniform). ``jacobian_floor``: the cap on
    ``1 / |cos e|`` near gimbal lock (module docstring; 0 for the exact pushforward).
    """

    def __init__(
        self,
        mu: torch.Tensor,
        kappa: torch.Tensor,
        weights: torch.Tensor | None = None,
        *,
        log_weights: torch.Tensor | None = None,
        jacobian_floor: float = JACOBIAN_FLOOR,
    ):
        if (
            isinstance(jacobian_floor, bool)
            or not isinstance(jacobian_floor, (int, float))
            or not 0 <= jacobian_floor < 1
        ):
            raise ConfigError(f"jacobian_floor must be a number in [0, 1), got {jacobian_floor!r}")
        if mu.ndim != 4 or mu.shape[-2:] != (3, 2):
            raise ConfigError(f"mu must have shape (B, C, 3, 2) (biternions), got {tuple(mu.shape)}")
        if not mu.is_floating_point():
            raise ConfigError(f"mu must be a floating point tensor, got {mu.dtype}")
        B, C = mu.shape[:2]
        if kappa.shape != (B, C, 3):
            raise ConfigError(f"kappa must have shape (B, C, 3) = {(B, C, 3)}, got {tuple(kappa.shape)}")
        with torch.no_grad():
            if not torch.isfinite(kappa).all() or (kappa <= 0).any():
                raise ConfigError(f"kappa of shape {tuple(kappa.shape)} must be finite and > 0")
            if not torch.isfinite(mu).all() or (torch.linalg.vector_norm(mu, dim=-1) < 1e-6).any():
                raise ConfigError(f"mu of shape {tuple(mu.shape)} must be finite non-zero (cos, sin) pairs")
        if weights is not None and log_weights is not None:
            raise ConfigError("give weights or log_weights, not both")
        if weights is not None:
            if weights.shape != (B, C):
                raise ConfigError(f"weights must have shape (B, C) = {(B, C)}, got {tuple(weights.shape)}")
            log_weights = torch.log(weights.clamp_min(torch.finfo(weights.dtype).tiny))
        if log_weights is None:
            log_weights = torch.full((B, C), -math.log(C), dtype=mu.dtype, device=mu.device)
        if log_weights.shape != (B, C):
            raise ConfigError(f"log_weights must have shape (B, C) = {(B, C)}, got {tuple(log_weights.shape)}")
        self.mu = mu / torch.linalg.vector_norm(mu, dim=-1, keepdim=True)
        self.kappa = kappa.to(mu.dtype)
        self.log_weights = log_weights.to(mu.dtype)
        self.num_components = C
        self.jacobian_floor = float(jacobian_floor)
        self.batch_size, self.dtype, self.device = B, mu.dtype, mu.device

    @classmethod
    def from_output(cls, x: torch.Tensor, num_components: int = 1, **kwargs) -> VonMisesEuler:
        """The distribution of a raw network output ``(B, C * 10)`` (:func:`von_mises_params_from_output`)."""
        mu, kappa, log_w = _params(x, num_components)
        return cls(mu, kappa, log_weights=log_w, **kwargs)

    @property
    def weights(self) -> torch.Tensor:
        """Mixture weights ``(B, C)``."""
        return self.log_weights.exp()

    def component_log_normalizers(self) -> torch.Tensor:
        """``sum_i log(2 pi I0(kappa_i))`` per component ``(B, C)``: the log normaliser of
        ``exp(sum_i kappa_i cos(x_i - mu_i))`` on the torus, and (module docstring) on SO(3)."""
        return von_mises_log_normalizer(self.kappa).sum(-1)

    def component_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """Normalised SO(3) log density of each component at ``(K, 3, 3)`` or ``(B, K, 3, 3)``: ``(B, C, K)``."""
        if rotations.ndim not in (3, 4) or rotations.shape[-2:] != (3, 3):
            raise ConfigError(f"rotations must have shape (B, K, 3, 3) or (K, 3, 3), got {tuple(rotations.shape)}")
        R = rotations.to(self.dtype)
        angles = torch.stack(matrix_to_aet_biternions(R), dim=-2)  # [(B,) K, 3, 2] (a, e, t)
        # cos(x_i - mu_i) = cos x cos mu + sin x sin mu, per angle  [B, C, K, 3]
        if R.ndim == 3:
            cos_diff = torch.einsum("bcid,kid->bcki", self.mu, angles)
        else:
            cos_diff = torch.einsum("bcid,bkid->bcki", self.mu, angles)
        # the other preimage (a + pi, pi - e, t + pi): cos(x - mu) -> -cos(a - mu_a), -cos(e + mu_e), -cos(t - mu_t)
        mu_other = self.mu * torch.tensor(
            [[-1.0, -1.0], [-1.0, 1.0], [-1.0, -1.0]], dtype=self.dtype, device=self.device
        )
        if R.ndim == 3:
            cos_other = torch.einsum("bcid,kid->bcki", mu_other, angles)
        else:
            cos_other = torch.einsum("bcid,bkid->bcki", mu_other, angles)
        k = self.kappa[:, :, None, :]  # [B, C, 1, 3]
        log_f = torch.logaddexp((k * (cos_diff - 1)).sum(-1), (k * (cos_other - 1)).sum(-1))  # [B, C, K]
        log_norm = (LOG_2PI + torch.log(torch.special.i0e(self.kappa))).sum(-1)  # [B, C] (kappa cancelled)
        cos_e = angles[..., 1, 0].clamp_min(max(self.jacobian_floor, torch.finfo(self.dtype).eps))  # [(B,) K]
        log_jacobian = torch.log(cos_e) - math.log(8.0)  # log(|cos e| / 8)  [(B,) K]
        if R.ndim == 3:
            log_jacobian = log_jacobian[None]
        return log_f - log_norm[..., None] - log_jacobian[:, None, :]

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """The (already normalised) mixture log density ``log sum_c w_c p_c(R)``: ``(B, K)``."""
        return torch.logsumexp(self.component_log_density(rotations) + self.log_weights[..., None], dim=1)

    def exact_log_normalizer(self) -> torch.Tensor:
        """0 ``(B,)``: :meth:`unnormalized_log_density` is already normalised (per component)."""
        return torch.zeros(self.batch_size, dtype=self.dtype, device=self.device)

    def component_means(self) -> torch.Tensor:
        """The rotation of each component's mean angles, ``(B, C, 3, 3)``."""
        return aet_biternions_to_matrix(*self.mu.unbind(-2))

    def exact_mode(self) -> torch.Tensor:
        """``(B, 3, 3)``: of the component means, the one where the mixture's SO(3) density is highest.

        The mean is the peak of a component's angle density; on SO(3) the Jacobian ``8 / |cos e|``
        moves the peak by ``O(tan(mu_e) / kappa_e)`` in elevation (none at ``mu_e = 0``), and the
        density is unbounded at ``cos e = 0``, so this is the mode of the angle density.
        """
        means = self.component_means()  # [B, C, 3, 3]
        if self.num_components == 1:
            return means[:, 0]
        with torch.no_grad():
            best = self.unnormalized_log_density(means).argmax(dim=1)  # [B]
        return means[torch.arange(self.batch_size, device=self.device), best]

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)``: a component per draw, the three angles from their von
        Mises (:func:`sample_von_mises`), then :func:`~image2sphere.so3.rotations.aet_to_matrix`."""
        check_int("n", n, 1)
        B = self.batch_size
        with torch.no_grad():
            comp = torch.multinomial(self.weights.double().cpu(), n, replacement=True, generator=generator)
            comp = comp.to(self.device)  # [B, n]
            idx = torch.arange(B, device=self.device)[:, None]
            mu = self.mu.double()[idx, comp]  # [B, n, 3, 2]
            mean_angle = torch.atan2(mu[..., 1], mu[..., 0])  # [B, n, 3]
            angles = sample_von_mises(mean_angle, self.kappa[idx, comp], generator)  # [B, n, 3]
            return aet_to_matrix(*angles.unbind(-1)).to(self.dtype)


def von_mises_nll(dist_or_output: VonMisesEuler | torch.Tensor, rotation: torch.Tensor, num_components: int = 1):
    """Negative log likelihood ``(B,)`` of ``rotation (B, 3, 3)`` under a :class:`VonMisesEuler` or the
    distribution of a raw output ``(B, C * 10)`` (Haar measure of volume ``pi^2``; mean it for a loss).

    It differs from Prokudin et al.'s loss (the angle log likelihood on the torus) by the
    parameter-free ``log(8 / |cos e|)`` and the folding of the two preimages."""
    dist = dist_or_output
    if not isinstance(dist, VonMisesEuler):
        dist = VonMisesEuler.from_output(dist_or_output, num_components)
    check_labels(rotation, dist.batch_size)
    check_rotation_matrix(rotation, "rotation", atol=1e-3)
    return -dist.unnormalized_log_density(rotation[:, None].to(dist.dtype))[:, 0]
