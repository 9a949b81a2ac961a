"""Point regressors that mix classification and regression (the older rows of the I2S paper's tables).

* :class:`SphericalRegression`: Liao, Gavves & Snoek 2019, "Spherical regression: learning
  viewpoints, surface normals and 3D rotations on n-spheres" (CVPR), the quaternion (``S^3``)
  version the I2S paper runs on ModelNet10-SO(3). The unit quaternion ``q = (w, x, y, z)`` with
  ``w >= 0`` is split into its absolute values, regressed on the sphere by the *spherical
  exponential* ``|q| = sqrt(softmax(o))`` (4 outputs), and its signs, classified among the 8 sign
  patterns of ``(x, y, z)`` (8 outputs). Loss: ``abs_weight * (1 - <|q|_pred, |q|_true>)`` (cosine
  proximity; the authors weight it by 10) plus the cross-entropy of the sign class.
* :class:`BinDeltaRegression`: Mahendran, Ali & Vidal 2018, "A mixed classification-regression
  framework for 3D pose estimation from 2D images" (BMVC), the "Bin & Delta" model: the rotations
  are split into ``K`` pose bins with centres ``R_k``; one head classifies the bin, the other
  regresses, per bin, a correction ``delta_k`` (axis-angle, 3 numbers), and the prediction is
  ``R_k exp([delta_k]_x)`` for the most likely bin ``k``. Loss: the bin cross-entropy (label: the
  bin nearest the true rotation) plus ``delta_weight`` times the geodesic angle between the true
  rotation and the corrected centre of its own bin. The bin centres here are the SO(3) HEALPix grid
  of ``bin_level`` (level 0: 72 equal-volume bins, level 1: 576), fixed before training; the
  authors cluster the training rotations with K-means (24 to 200 bins), which needs the training
  set before the network exists.

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; quaternions ``(..., 4)`` in ``(w, x, y, z)``
  order (:func:`~image2sphere.so3.rotations.quaternion_to_matrix` and
  :func:`~image2sphere.so3.rotations.matrix_to_quaternion` with ``"wxyz"``).
* Both networks output one tensor per image (the layout in each class) whose distribution is a
  :class:`~image2sphere.distributions.base.PointEstimate`: no density, so the log likelihood and the
  spread are reported as not available.
* As in the authors' code, with ``num_classes > 0`` each class has its own last layers
  (:class:`~image2sphere.nn.regression.PerClassLinear`), selected by the class index.
"""

from __future__ import annotations

import itertools

import torch
import torch.nn.functional as F
from torch import nn

from image2sphere.checks import ConfigError, check_int, check_number
from image2sphere.distributions.base import PointEstimate
from image2sphere.nn.base import PoseNetwork
from image2sphere.nn.regression import PerClassLinear
from image2sphere.so3.grid import check_level, so3_healpix_grid, so3_healpix_nearest_index
from image2sphere.so3.rotations import geodesic_distance, matrix_to_quaternion, quaternion_to_matrix, rotvec_to_matrix

__all__ = [
    "QUATERNION_SIGNS",
    "BinDeltaRegression",
    "SphericalRegression",
    "quaternion_sign_class",
]

#: the 8 sign patterns of a quaternion with ``w >= 0``: ``(1, sx, sy, sz)``, class ``c`` is row ``c``
QUATERNION_SIGNS = torch.tensor([(1.0, *s) for s in itertools.product((-1.0, 1.0), repeat=3)])


def quaternion_sign_class(q: torch.Tensor) -> torch.Tensor:
    """Sign class ``(...)`` in ``0..7`` of quaternions ``q (..., 4)`` with ``w >= 0`` (a zero counts
    as positive): the row of :data:`QUATERNION_SIGNS` with the signs of ``(x, y, z)``."""
    negative = (q[..., 1:] < 0).long()  # [..., 3]; the product order puts -1 first
    return 4 * (1 - negative[..., 0]) + 2 * (1 - negative[..., 1]) + (1 - negative[..., 2])


def _mlp(in_features: int, hidden: int, out_features: int, num_classes: int) -> tuple[nn.Module, PerClassLinear]:
    return nn.Sequential(nn.Linear(in_features, hidden), nn.ReLU()), PerClassLinear(hidden, out_features, num_classes)


class _ClassRegressionNet(PoseNetwork):
    """Pooled encoder features -> two heads (each a hidden layer and per-class last layers), their
    outputs concatenated: ``[B, sum of the heads' outputs]``."""

    def __init__(self, encoder: nn.Module, image_size, hidden: int, num_classes: int, out_features: tuple[int, int]):
        super().__init__(encoder, image_size, num_classes=0)
        check_int("hidden", hidden, 1)
        self.num_classes = check_int("num_classes", num_classes, 0)  # per-class last layers
        self.hidden_a, self.last_a = _mlp(self.feature_channels, hidden, out_features[0], num_classes)
        self.hidden_b, self.last_b = _mlp(self.feature_channels, hidden, out_features[1], num_classes)

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        pooled = self.encode(images).mean(dim=(-1, -2))  # [B, C] (float32 under autocast)
        onehot = self.class_onehot(class_index, len(pooled)) if self.num_classes else None  # [B, nc]
        return torch.cat([self.last_a(self.hidden_a(pooled), onehot), self.last_b(self.hidden_b(pooled), onehot)], 1)

    def _check_output(self, output: torch.Tensor, width: int) -> torch.Tensor:
        if not isinstance(output, torch.Tensor) or output.ndim != 2 or output.shape[1] != width:
            raise ConfigError(
                f"{type(self).__name__} output must have shape (B, {width}), got {tuple(getattr(output, 'shape', ()))}"
            )
        return output


class SphericalRegression(_ClassRegressionNet):
    """Liao et al. 2019: quaternion by spherical-exponential regression of ``|q|`` and classification
    of its signs (module docstring). Output ``(B, 12)``: 4 logits of ``|q|^2``, then 8 sign logits.

    Args:
        encoder: the image encoder (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the input size the network is built for.
        hidden: width of each head's hidden layer (the authors' code: 996).
        abs_weight: weight of the cosine-proximity loss of ``|q|`` (the authors': 10).
        num_classes: > 0: one last layer per class, chosen by the class index.
    """

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 996,
                 abs_weight: float = 10.0, num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, hidden, num_classes, (4, len(QUATERNION_SIGNS)))
        self.abs_weight = check_number("abs_weight", abs_weight)

    def quaternion(self, output: torch.Tensor) -> torch.Tensor:
        """The predicted unit quaternions ``(B, 4)`` (``w >= 0``): ``|q|`` times the likeliest signs."""
        output = self._check_output(output, 12)
        magnitude = torch.softmax(output[:, :4], dim=1).sqrt()  # [B, 4], unit norm
        signs = QUATERNION_SIGNS.to(output)[output[:, 4:].argmax(dim=1)]  # [B, 4]
        return magnitude * signs

    def output_distribution(self, output: torch.Tensor) -> PointEstimate:
        return PointEstimate(quaternion_to_matrix(self.quaternion(output), "wxyz"))

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """``abs_weight * (1 - cos(|q|, |q_true|)) + CE(signs)`` per image ``(B,)``; ``grid_level`` is unused."""
        output = self._check_output(output, 12)
        q = matrix_to_quaternion(rotation.to(output.dtype), "wxyz")  # [B, 4], w >= 0
        magnitude = torch.softmax(output[:, :4], dim=1).clamp_min(torch.finfo(output.dtype).tiny).sqrt()
        cosine = (magnitude * q.abs()).sum(dim=1)  # both unit vectors
        return self.abs_weight * (1 - cosine) + F.cross_entropy(
            output[:, 4:], quaternion_sign_class(q), reduction="none"
        )


class BinDeltaRegression(_ClassRegressionNet):
    """Mahendran et al. 2018, the "Bin & Delta" model (module docstring). Output ``(B, 4 K)``: ``K``
    bin logits, then ``K`` axis-angle corrections ``(K, 3)`` flattened.

    Args:
        encoder: the image encoder (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the input size the network is built for.
        hidden: width of each head's hidden layer.
        bin_level: the SO(3) HEALPix level of the bin centres (0: 72 bins, 1: 576, 2: 4,608).
        delta_weight: weight of the geodesic loss of the corrected bin centre.
        num_classes: > 0: one last layer per class, chosen by the class index.
    """

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 bin_level: int = 0, delta_weight: float = 1.0, num_classes: int = 0):  # fmt: skip
        level = check_level(bin_level, "bin_level", max_level=2, purpose="pose bins")
        centres = so3_healpix_grid(level)  # [K, 3, 3]
        super().__init__(encoder, image_size, hidden, num_classes, (len(centres), 3 * len(centres)))
        self.bin_level = level
        self.delta_weight = check_number("delta_weight", delta_weight)
        self.register_buffer("centres", centres, persistent=False)
        with torch.no_grad():  # corrections start near zero: the first predictions are the bin centres
            self.last_b.weight.mul_(0.1)
            self.last_b.bias.zero_()

    @property
    def num_bins(self) -> int:
        return len(self.centres)

    def corrected(self, output: torch.Tensor, bins: torch.Tensor) -> torch.Tensor:
        """``R_k exp([delta_k]_x)`` ``(B, 3, 3)`` for one bin ``k`` per image ``bins (B,)``."""
        output = self._check_output(output, 4 * self.num_bins)
        delta = output[:, self.num_bins :].reshape(len(output), self.num_bins, 3)  # [B, K, 3]
        chosen = delta.gather(1, bins[:, None, None].expand(-1, 1, 3))[:, 0]  # [B, 3]
        return self.centres.to(output.dtype)[bins] @ rotvec_to_matrix(chosen)  # [B, 3, 3]

    def output_distribution(self, output: torch.Tensor) -> PointEstimate:
        output = self._check_output(output, 4 * self.num_bins)
        return PointEstimate(self.corrected(output, output[:, : self.num_bins].argmax(dim=1)))

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """Bin cross-entropy plus ``delta_weight`` times the geodesic angle (radians) of the true bin's
        corrected centre, per image ``(B,)``; ``grid_level`` is unused."""
        output = self._check_output(output, 4 * self.num_bins)
        rotation = rotation.to(output.dtype)
        true_bin = so3_healpix_nearest_index(rotation.detach(), self.bin_level).to(output.device)  # [B]
        ce = F.cross_entropy(output[:, : self.num_bins], true_bin, reduction="none")
        return ce + self.delta_weight * geodesic_distance(self.corrected(output, true_bin), rotation)
