"""Rotation regression baselines: a ResNet, spatial pooling, two linear layers, a rotation.

* ``representation="6d"``: Zhou et al. 2019, "On the continuity of rotation representations in
  neural networks": two 3-vectors, orthonormalised by Gram-Schmidt into the first two columns of
  ``R`` (the third is their cross product) (:func:`rotation_6d_to_matrix`).
* ``representation="9d"``: Levinson et al. 2020 / Brégier 2021, "Deep regression on manifolds: a 3D
  rotation case study": a 3x3 matrix projected onto SO(3) by the special orthogonal Procrustes
  problem (nearest rotation in the Frobenius norm, through an SVD) (:func:`special_procrustes`).

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

from image2sphere.distributions.base import PointEstimate
from image2sphere.nn.base import PoseNetwork
from image2sphere.so3.rotations import geodesic_distance

__all__ = ["PerClassLinear", "RotationRegression", "rotation_6d_to_matrix", "special_procrustes"]

REPRESENTATIONS = {"6d": 6, "9d": 9}
LOSSES = ("frobenius", "geodesic")


def rotation_6d_to_matrix(x: torch.Tensor) -> torch.Tensor:
    """Zhou et al.'s 6D representation ``(..., 6)`` -> rotation ``(..., 3, 3)``: the two 3-vectors
    ``a = x[..., :3]``, ``b = x[..., 3:]`` are orthonormalised by Gram-Schmidt into the columns
    ``c1 = a / |a|``, ``c2 = normalise(b - <c1, b> c1)``, ``c3 = c1 x c2``."""
    if x.shape[-1] != 6:
        raise ValueError(f"a 6D rotation representation must have shape (..., 6), got {tuple(x.shape)}")
    a, b = x[..., :3], x[..., 3:]
    c1 = nn.functional.normalize(a, dim=-1)
    c2 = nn.functional.normalize(b - (c1 * b).sum(-1, keepdim=True) * c1, dim=-1)
    c3 = torch.cross(c1, c2, dim=-1)
    return torch.stack([c1, c2, c3], dim=-1)  # columns


class _SpecialProcrustes(torch.autograd.Function):
    """``R = U diag(1, 1, det(U V^T)) V^T`` for ``M = U S V^T``, with the gradient of the polar factor.

    Writing ``M = R P`` with ``P = V L V^T`` symmetric, ``L = diag(s1, s2, d s3)``, a change ``dM``
    moves ``R`` by ``R V w V^T`` with ``w_ij = a_ij / (l_i + l_j)`` and ``a = V^T (R^T dM - dM^T R) V``:
    the denominators are sums of singular values, not the differences in the generic SVD gradient, so
    the gradient stays finite when singular values coincide (e.g. ``M`` a rotation). Only
    ``l_i + l_j = 0`` (a reflection-like ``M`` with ``s2 = s3``) is singular; it is clamped.
    """

    @staticmethod
    def forward(ctx, M: torch.Tensor) -> torch.Tensor:
        U, S, Vh = torch.linalg.svd(M)
        d = torch.det(U @ Vh)  # [...]
        D = torch.ones_like(S)
        D[..., 2] = d
        R = U @ (D[..., :, None] * Vh)
        ctx.save_for_backward(R, Vh.transpose(-1, -2), S * D)
        return R

    @staticmethod
    def backward(ctx, G: torch.Tensor) -> torch.Tensor:
        R, V, L = ctx.saved_tensors
        H = V.transpose(-1, -2) @ R.transpose(-1, -2) @ G @ V  # [..., 3, 3]
        denom = L[..., :, None] + L[..., None, :]
        eps = torch.finfo(L.dtype).eps * L.abs().amax(-1, keepdim=True)[..., None].clamp_min(1.0)
        denom = torch.where(denom.abs() < eps, torch.where(denom < 0, -eps, eps), denom)
        K = H / denom
        return R @ V @ (K - K.transpose(-1, -2)) @ V.transpose(-1, -2)


def special_procrustes(M: torch.Tensor) -> torch.Tensor:
    """The rotation nearest ``M (..., 3, 3)`` in the Frobenius norm, with a stable gradient."""
    if M.ndim < 2 or M.shape[-2:] != (3, 3):
        raise ValueError(f"M must have shape (..., 3, 3), got {tuple(M.shape)}")
    return _SpecialProcrustes.apply(M)


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
            raise ValueError(f"representation must be one of {sorted(REPRESENTATIONS)}, got {representation!r}")
        if loss not in LOSSES:
            raise ValueError(f"loss must be one of {LOSSES}, got {loss!r}")
        if isinstance(hidden, bool) or not isinstance(hidden, int) or hidden < 1:
            raise ValueError(f"hidden must be a positive integer, got {hidden!r}")
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
        return special_procrustes(x.reshape(-1, 3, 3))

    def output_distribution(self, output: torch.Tensor) -> PointEstimate:
        return PointEstimate(output)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """``|R - R_gt|_F^2`` (or the geodesic angle) per image ``(B,)``; ``grid_level`` is unused."""
        rotation = rotation.to(output.dtype)
        if self.loss_kind == "geodesic":
            return geodesic_distance(output, rotation)
        return (output - rotation).pow(2).sum(dim=(-1, -2))
