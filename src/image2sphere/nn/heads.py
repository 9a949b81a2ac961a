"""Parametric density baselines: a ResNet, spatial pooling, an MLP, the parameters of a family.

Each network here is the same small head on the pooled encoder features (one hidden layer of
``hidden`` units, ReLU, a linear layer to the family's parameters) and differs only in the family its
output parametrises and the family's negative log likelihood, its training loss:

================================  ===========================================  =====================
network                           family (:mod:`image2sphere.distributions`)   output per image
================================  ===========================================  =====================
:class:`MatrixFisherNet`          matrix Fisher (Mohlin et al. 2020)           ``F``, 9 numbers
:class:`RotationLaplaceNet`       Rotation Laplace (Yin et al. 2023)           ``A``, 9 numbers
:class:`BinghamNet`               Bingham mixture (Gilitschenski et al. 2020;  8 per component
                                  Deng et al. 2022 for ``num_components > 1``)
:class:`VonMisesNet`              von Mises mixture on Euler angles            10 per component
                                  (Prokudin et al. 2018)
:class:`ViewpointBinsNet`         Euler-angle bins (Tulsiani & Malik 2015)     3 x ``num_bins``
================================  ===========================================  =====================

Densities are w.r.t. the Haar measure of volume ``pi^2``; every family is also scored by the grid
protocol of I2S (docs/evaluation.md) and reports its closed-form density where it has one.
"""

from __future__ import annotations

import torch
from torch import nn

from image2sphere.checks import check_int
from image2sphere.distributions.base import check_num_components
from image2sphere.distributions.bingham import Bingham, bingham_nll
from image2sphere.distributions.euler_bins import EulerBins, check_num_bins, euler_bins_nll
from image2sphere.distributions.matrix_fisher import MatrixFisher, matrix_fisher_nll
from image2sphere.distributions.rotation_laplace import RotationLaplace, rotation_laplace_nll
from image2sphere.distributions.von_mises import VonMisesEuler, von_mises_nll
from image2sphere.nn.base import PoseNetwork

__all__ = [
    "BinghamNet",
    "EulerBinsNet",
    "MatrixFisherNet",
    "ParametricHead",
    "RotationLaplaceNet",
    "VonMisesNet",
    "ViewpointBinsNet",
]


class ParametricHead(PoseNetwork):
    """Pooled encoder features (with the class one-hot when ``num_classes > 0``) -> ``hidden`` units
    -> ReLU -> ``out_features`` raw parameters. The last layer starts small (weights x
    ``init_scale``) so that every family starts close to a broad distribution.

    Args:
        encoder: the image encoder (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the input size the network is built for.
        out_features: number of raw parameters per image (set by each family's network).
        hidden: width of the hidden layer.
        num_classes: > 0: the class one-hot is appended to the features.
        init_scale: factor on the last layer's initial weights.
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int],
        out_features: int,
        hidden: int = 512,
        num_classes: int = 0,
        init_scale: float = 0.1,
    ):
        super().__init__(encoder, image_size, num_classes)
        check_int("hidden", hidden, 1)
        last = nn.Linear(hidden, out_features)
        with torch.no_grad():
            last.weight.mul_(init_scale)
            last.bias.zero_()
        self.mlp = nn.Sequential(nn.Linear(self.feature_channels, hidden), nn.ReLU(), last)

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` -> raw parameters ``[B, out_features]``."""
        return self.mlp(self.pooled_features(images, class_index))  # [B, C] -> [B, out]


class MatrixFisherNet(ParametricHead):
    """Mohlin et al. 2020, "Probabilistic orientation estimation with matrix Fisher distributions"
    (NeurIPS): ``p(R) prop. to exp(tr(F^T R))``, trained by its negative log likelihood."""

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, 9, hidden, num_classes)

    def output_distribution(self, output: torch.Tensor) -> MatrixFisher:
        return MatrixFisher(output.reshape(-1, 3, 3))

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        return matrix_fisher_nll(output.reshape(-1, 3, 3), rotation)


class RotationLaplaceNet(ParametricHead):
    """Yin et al. 2023, "A Laplace-inspired distribution on SO(3) for probabilistic rotation
    estimation" (ICLR): ``p(R) prop. to exp(-sqrt(t)) / sqrt(t)``, ``t = tr(S - A^T R)``."""

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, 9, hidden, num_classes)

    def output_distribution(self, output: torch.Tensor) -> RotationLaplace:
        return RotationLaplace(output.reshape(-1, 3, 3))

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        return rotation_laplace_nll(output.reshape(-1, 3, 3), rotation)


class BinghamNet(ParametricHead):
    """Gilitschenski et al. 2020, "Deep orientation uncertainty learning based on a Bingham loss"
    (ICLR); with ``num_components > 1`` the Bingham mixture of Deng et al. 2022, "Deep Bingham
    networks" (IJCV). Output layout: :func:`~image2sphere.distributions.bingham.bingham_params_from_output`."""

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 num_components: int = 1, num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, 8 * check_num_components(num_components), hidden, num_classes)
        self.num_components = num_components

    def output_distribution(self, output: torch.Tensor) -> Bingham:
        return Bingham.from_output(output, self.num_components)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        return bingham_nll(output, rotation, self.num_components)


class VonMisesNet(ParametricHead):
    """Prokudin et al. 2018, "Deep directional statistics: pose estimation with uncertainty
    quantification" (ECCV): a mixture of products of von Mises distributions on three Euler angles
    (biternion outputs), as a density on SO(3). Output layout:
    :func:`~image2sphere.distributions.von_mises.von_mises_params_from_output`."""

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 num_components: int = 1, num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, 10 * check_num_components(num_components), hidden, num_classes)
        self.num_components = num_components

    def output_distribution(self, output: torch.Tensor) -> VonMisesEuler:
        return VonMisesEuler.from_output(output, self.num_components)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        return von_mises_nll(output, rotation, self.num_components)


class ViewpointBinsNet(ParametricHead):
    """Tulsiani & Malik 2015, "Viewpoints and keypoints" (CVPR): azimuth, elevation and tilt each
    classified into ``num_bins`` bins (the paper: 21), as a piecewise-constant density on SO(3)
    (:mod:`image2sphere.distributions.euler_bins`), trained by the three cross-entropies. Output
    layout: ``(B, 3 * num_bins)``, the azimuth, elevation and tilt logits in turn."""

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int] = 224, hidden: int = 512,
                 num_bins: int = 21, num_classes: int = 0):  # fmt: skip
        super().__init__(encoder, image_size, 3 * check_num_bins(num_bins), hidden, num_classes)
        self.num_bins = num_bins

    def output_distribution(self, output: torch.Tensor) -> EulerBins:
        return EulerBins.from_output(output, self.num_bins)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        return euler_bins_nll(output, rotation, self.num_bins)


#: the old name of :class:`ViewpointBinsNet` (``model=viewpoint_bins``), kept so that checkpoints whose
#: stored config names ``image2sphere.nn.EulerBinsNet`` still load
EulerBinsNet = ViewpointBinsNet
