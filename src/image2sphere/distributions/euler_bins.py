"""Viewpoint classification: independent categorical distributions over bins of three Euler angles,
as a piecewise-constant density on SO(3).

Baseline: Tulsiani & Malik 2015, "Viewpoints and keypoints" (CVPR): the azimuth, elevation and
in-plane rotation (tilt) of the object are each classified into bins, and the prediction is the
rotation of the most likely bins.

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``.
* **Euler angles** ``(a, e, t)``: the PASCAL3D+ viewpoint chart (AET angles) of
  :mod:`image2sphere.distributions.von_mises`, ``R = Rx(-t) @ Ry(-e) @ Rz(-a)``
  (:func:`~image2sphere.so3.rotations.aet_to_matrix`), read with ``e`` in
  ``[-pi/2, pi/2]`` (``cos e >= 0``), where every rotation has one chart point (up to the
  measure-zero circles ``e = +-pi/2``).
* **Bins**: ``n`` equal bins per angle: azimuth and tilt over ``[0, 2 pi)`` (bin ``k`` is
  ``[2 pi k / n, 2 pi (k + 1) / n)``), elevation over ``[-pi/2, pi/2]`` (bin ``k`` is
  ``[-pi/2 + pi k / n, -pi/2 + pi (k + 1) / n)``). A box is one bin of each angle.
* **Density** w.r.t. the Haar measure of volume ``pi^2``, which is ``cos e da de dt / 8`` in this
  chart: each box gets the product of its three bin probabilities, spread uniformly over the box, so

      p(R) = P_a[i] P_e[j] P_t[k] / V_j,    V_j = (2 pi / n)^2 (sin e_hi(j) - sin e_lo(j)) / 8,

  with ``(i, j, k)`` the box of ``R``. The boxes' volumes sum to ``pi^2`` and the probabilities to
  1, so the density is normalised exactly (:meth:`EulerBins.exact_log_normalizer` is 0). It is
  bounded: the boxes at the poles ``e = +-pi/2`` are small but not empty.
* The most likely box by probability and by density differ only through ``V_j`` (the elevation
  bins near the poles are smaller): :meth:`EulerBins.exact_mode` is the centre of the box of highest
  density, the peak the grid protocol finds.
* Training loss (:func:`euler_bins_nll`): the negative log density at the label, which is the sum
  of the three angles' cross-entropies (Tulsiani & Malik's loss) plus ``log V_j``, a term that does
  not depend on the network.
"""

from __future__ import annotations

import math

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution, check_temperature
from image2sphere.rotation_sets import check_labels
from image2sphere.so3.rotations import aet_to_matrix, check_rotation_matrix, matrix_to_aet_biternions

__all__ = ["EulerBins", "check_num_bins", "elevation_bin_log_volumes", "euler_bin_index", "euler_bins_nll"]

TWO_PI = 2 * math.pi


def check_num_bins(num_bins) -> int:
    """Bins per angle: an integer >= 1, else ``ValueError``."""
    return check_int("num_bins", num_bins, 1)


def elevation_bin_log_volumes(num_bins: int, dtype: torch.dtype = torch.float64, device=None) -> torch.Tensor:
    """``log V_j`` ``(num_bins,)``: the Haar volume (total ``pi^2``) of a box in elevation bin ``j``."""
    n = check_num_bins(num_bins)
    edges = torch.linspace(-math.pi / 2, math.pi / 2, n + 1, dtype=torch.float64)
    sin_width = torch.sin(edges[1:]) - torch.sin(edges[:-1])  # [n], > 0
    log_v = 2 * math.log(TWO_PI / n) + torch.log(sin_width) - math.log(8.0)
    return log_v.to(dtype=dtype, device=device)


def euler_bin_index(R: torch.Tensor, num_bins: int) -> torch.Tensor:
    """The box of each rotation ``R (..., 3, 3)``: bin indices ``(..., 3)`` of (azimuth, elevation, tilt)."""
    n = check_num_bins(num_bins)
    a, e, t = matrix_to_aet_biternions(R)  # each [..., 2] (cos, sin), cos e >= 0
    azimuth = torch.atan2(a[..., 1], a[..., 0]) % TWO_PI  # [0, 2 pi)
    tilt = torch.atan2(t[..., 1], t[..., 0]) % TWO_PI
    elevation = torch.atan2(e[..., 1], e[..., 0])  # [-pi/2, pi/2]
    frac = torch.stack([azimuth / TWO_PI, elevation / math.pi + 0.5, tilt / TWO_PI], dim=-1)  # [..., 3] in [0, 1]
    return (frac * n).floor().long().clamp(0, n - 1)


def _box_to_matrix(index: torch.Tensor, offset: torch.Tensor, num_bins: int, dtype: torch.dtype) -> torch.Tensor:
    """Rotations ``(..., 3, 3)`` at fractional position ``offset (..., 3)`` in ``[0, 1]`` inside the
    boxes ``index (..., 3)``; the elevation offset is a fraction of ``sin e`` between the bin's edges
    (so a uniform offset is uniform in the Haar measure)."""
    n = num_bins
    i = index.to(torch.float64)
    off = offset.to(torch.float64)
    azimuth = (i[..., 0] + off[..., 0]) * (TWO_PI / n)
    tilt = (i[..., 2] + off[..., 2]) * (TWO_PI / n)
    lo = -math.pi / 2 + i[..., 1] * (math.pi / n)
    hi = lo + math.pi / n
    sin_e = torch.sin(lo) + off[..., 1] * (torch.sin(hi) - torch.sin(lo))
    elevation = torch.asin(sin_e.clamp(-1.0, 1.0))
    return aet_to_matrix(azimuth, elevation, tilt).to(dtype)


class EulerBins(PoseDistribution):
    """A batch of ``B`` products of three categorical distributions over Euler-angle bins.

    Args:
        logits: ``(B, 3, n)``: the bin logits of azimuth, elevation and tilt (any real numbers; a
            softmax over the last axis gives each angle's bin probabilities).
    """

    def __init__(self, logits: torch.Tensor):
        if not isinstance(logits, torch.Tensor) or logits.ndim != 3 or logits.shape[1] != 3 or logits.shape[0] == 0:
            shape = tuple(logits.shape) if isinstance(logits, torch.Tensor) else type(logits).__name__
            raise ConfigError(f"Euler-bin logits must have shape (B, 3, num_bins) with B >= 1, got {shape}")
        if not logits.is_floating_point() or not torch.isfinite(logits.detach()).all():
            raise ConfigError("Euler-bin logits must be finite floating point numbers")
        self.num_bins = logits.shape[-1]
        self.log_probs = torch.log_softmax(logits, dim=-1)  # [B, 3, n]
        self.batch_size, self.dtype, self.device = logits.shape[0], logits.dtype, logits.device
        self.log_volumes = elevation_bin_log_volumes(self.num_bins, self.dtype, self.device)  # [n]

    @classmethod
    def from_output(cls, x: torch.Tensor, num_bins: int) -> EulerBins:
        """Raw network output ``x (B, 3 * num_bins)`` (azimuth, elevation, tilt logits in turn)."""
        n = check_num_bins(num_bins)
        if not isinstance(x, torch.Tensor) or x.ndim != 2 or x.shape[1] != 3 * n:
            raise ConfigError(
                f"Euler-bin output must have shape (B, {3 * n}) for {n} bins per angle, "
                f"got {tuple(getattr(x, 'shape', ()))}"
            )
        return cls(x.reshape(len(x), 3, n))

    def box_log_prob(self, index: torch.Tensor) -> torch.Tensor:
        """``log P_a[i] + log P_e[j] + log P_t[k]`` of boxes ``index (B, K, 3)``: ``(B, K)``."""
        # [B, 3, n] gathered at [B, 3, K] -> [B, 3, K], summed over the angles
        return self.log_probs.gather(2, index.transpose(1, 2)).sum(dim=1)

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """Log density ``(B, K)`` at ``(K, 3, 3)`` or ``(B, K, 3, 3)`` rotations (already normalised)."""
        rotations = self._check_query(rotations)
        index = euler_bin_index(rotations, self.num_bins)  # [(B,) K, 3]
        index = index.expand(self.batch_size, *index.shape[-2:]) if index.ndim == 2 else index
        return self.box_log_prob(index) - self.log_volumes[index[..., 1]]

    def exact_log_normalizer(self) -> torch.Tensor:
        return self.log_probs.new_zeros(self.batch_size)

    def tempered(self, temperature: float) -> EulerBins:
        """``p ** (1 / temperature)``, renormalised, exactly: the density ``P_a P_e P_t / V_e`` stays a product
        of three binned factors. Azimuth and tilt: their log probabilities divided by the temperature; the
        elevation: its log density ``log P_e - log V_e`` divided by it, and each bin's volume put back."""
        temperature = check_temperature(temperature)
        if temperature == 1.0:
            return self
        logits = self.log_probs / temperature  # [B, 3, n]
        elevation = (self.log_probs[:, 1] - self.log_volumes) / temperature + self.log_volumes  # [B, n]
        return EulerBins(torch.cat([logits[:, :1], elevation[:, None], logits[:, 2:]], dim=1))

    def mode_box(self) -> torch.Tensor:
        """The box of highest density ``(B, 3)`` (the three angles are independent, so per angle)."""
        azimuth = self.log_probs[:, 0].argmax(dim=-1)
        elevation = (self.log_probs[:, 1] - self.log_volumes).argmax(dim=-1)
        tilt = self.log_probs[:, 2].argmax(dim=-1)
        return torch.stack([azimuth, elevation, tilt], dim=-1)

    def exact_mode(self) -> torch.Tensor:
        """The centre of the box of highest density ``(B, 3, 3)`` (the density is flat on the box)."""
        box = self.mode_box()
        return _box_to_matrix(box, torch.full(box.shape, 0.5, dtype=torch.float64), self.num_bins, self.dtype)

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` draws ``(B, n, 3, 3)``: a bin per angle from its probabilities, then a point uniform
        (in the Haar measure) in the box."""
        check_int("n", n, 1)
        with torch.no_grad():
            probs = self.log_probs.detach().double().exp().reshape(-1, self.num_bins).cpu()  # [B * 3, nb]
            index = torch.multinomial(probs, n, replacement=True, generator=generator)  # [B * 3, n]
            index = index.reshape(self.batch_size, 3, n).transpose(1, 2)  # [B, n, 3]
            offset = torch.rand(index.shape, generator=generator, dtype=torch.float64)  # [B, n, 3]
            return _box_to_matrix(index, offset, self.num_bins, self.dtype).to(self.device)


def euler_bins_nll(output: torch.Tensor, rotation: torch.Tensor, num_bins: int) -> torch.Tensor:
    """Negative log density ``(B,)`` of ``rotation (B, 3, 3)`` under the network output ``(B, 3 * num_bins)``."""
    check_labels(rotation, len(output))
    check_rotation_matrix(rotation, "rotation", atol=1e-3)
    dist = EulerBins.from_output(output, num_bins)
    return -dist.unnormalized_log_density(rotation[:, None].to(output.dtype))[:, 0]
