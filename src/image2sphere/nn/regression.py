"""Rotation regression baselines: a ResNet, spatial pooling, two linear layers, a rotation.

* ``representation="6d"``: Zhou et al. 2019, "On the continuity of rotation representations in
  neural networks": two 3-vectors, orthonormalised by Gram-Schmidt into the first two columns of
  ``R`` (the third is their cross product)
  (:func:`~image2sphere.so3.rotations.rotation_6d_to_matrix`).
* ``representation="9d"``: Levinson et al. 2020 / Brégier 2021, "Deep regression on manifolds: a 3D
  rotation case study": a 3x3 matrix projected onto SO(3) by the special orthogonal Procrustes
  problem (nearest rotation in the Frobenius norm, through an SVD)
  (:func:`~image2sphere.so3.rotations.project_to_so3`).

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; the network's output is one rotation per
  image, so its distribution is a :class:`~image2sphere.distributions.base.PointEstimate` (no
  density: log likelihood and spread are reported as not available).
* Loss (the paper's appendix): the squared Frobenius distance ``|R - R_gt|_F^2``, or with
  ``loss="geodesic"`` the geodesic angle in radians.
* As in the paper's implementation, with ``num_classes > 0`` each class has its own last linear
  layer (selected by the class index), instead of a class one-hot input.
"""

from __future__ import annotations

import torch
from torch import nn

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PointEstimate
from image2sphere.nn.base import PoseNetwork
from image2sphere.so3.rotations import geodesic_distance, project_to_so3, rotation_6d_to_matrix

__all__ = ["PerClassLinear", "RotationRegression"]

REPRESENTATIONS = {"6d": 6, "9d": 9}
LOSSES = ("frobenius", "geodesic")


class PerClassLinear(nn.Linear):
    """The last layer of the regression baselines: ``out_features`` outputs, or with ``num_classes > 0``
    one set of ``out_features`` per class, of which each image gets its own class's (the papers'
    class-specific output layers instead of a class one-hot input).

    Args:
        in_features: inputs per image.
        out_features: outputs per image.
        num_classes: 0: one layer for all images; > 0: one per class.
    """

    def __init__(self, in_features: int, out_features: int, num_classes: int = 0):
        super().__init__(in_features, out_features * max(1, num_classes))
        self.out_per_class, self.num_classes = out_features, num_classes

    def forward(self, x: torch.Tensor, onehot: torch.Tensor | None = None) -> torch.Tensor:
        """``x [B, in]`` (and the class one-hot ``[B, nc]`` when ``num_classes > 0``) -> ``[B, out]``."""
        y = super().forward(x)  # [B, out * max(1, nc)]
        if not self.num_classes:
            return y
        y = y.reshape(len(y), self.num_classes, self.out_per_class)  # [B, nc, out]
        return torch.einsum("bco,bc->bo", y, onehot.to(y.dtype))  # [B, out]


class RotationRegression(PoseNetwork):
    """A point regressor: pooled encoder features -> two linear layers -> a rotation.

    Args:
        encoder: the image encoder (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the input size the network is built for.
        representation: ``"6d"`` (Zhou et al. 2019, Gram-Schmidt) or ``"9d"`` (Brégier 2021,
            Procrustes).
        hidden: width of the hidden linear layer (the paper: two linear layers).
        loss: ``"frobenius"`` (the paper's L2 loss on the matrix) or ``"geodesic"``.
        num_classes: > 0: one last linear layer per class, chosen by the class index.
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        representation: str = "6d",
        hidden: int = 512,
        loss: str = "frobenius",
        num_classes: int = 0,
    ):
        if representation not in REPRESENTATIONS:
            raise ConfigError(f"representation must be one of {sorted(REPRESENTATIONS)}, got {representation!r}")
        if loss not in LOSSES:
            raise ConfigError(f"loss must be one of {LOSSES}, got {loss!r}")
        check_int("hidden", hidden, 1)
        super().__init__(encoder, image_size, num_classes=0)
        self.num_classes = num_classes  # per-class output layers, not one-hot input channels
        self.representation, self.loss_kind = representation, loss
        self.out_dim = REPRESENTATIONS[representation]
        self.hidden = nn.Sequential(nn.Linear(self.feature_channels, hidden), nn.ReLU())
        self.last = PerClassLinear(hidden, self.out_dim, num_classes)

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` -> rotations ``[B, 3, 3]``."""
        pooled = self.encode(images).mean(dim=(-1, -2))  # [B, C] (float32 under autocast)
        onehot = self.class_onehot(class_index, len(pooled)) if self.num_classes else None  # [B, nc]
        x = self.last(self.hidden(pooled), onehot)  # [B, d]
        if self.representation == "6d":
            return rotation_6d_to_matrix(x)
        return project_to_so3(x.reshape(-1, 3, 3))

    def output_distribution(self, output: torch.Tensor) -> PointEstimate:
        return PointEstimate(output)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """``|R - R_gt|_F^2`` (or the geodesic angle) per image ``(B,)``; ``grid_level`` is unused."""
        rotation = rotation.to(output.dtype)
        if self.loss_kind == "geodesic":
            return geodesic_distance(output, rotation)
        return (output - rotation).pow(2).sum(dim=(-1, -2))
