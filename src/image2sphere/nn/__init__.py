"""Neural network modules: encoders, image-to-sphere projectors, S2/SO(3) convolutions, pose networks."""

from image2sphere.nn.activation import SO3ReLU
from image2sphere.nn.base import PoseNetwork
from image2sphere.nn.classification_regression import BinDeltaRegression, SphericalRegression
from image2sphere.nn.encoder import RESNET_DEPTHS, ResNetEncoder, TorchvisionEncoder
from image2sphere.nn.heads import (
    BinghamNet,
    EulerBinsNet,
    MatrixFisherNet,
    RotationLaplaceNet,
    ViewpointBinsNet,
    VonMisesNet,
)
from image2sphere.nn.i2s import I2S, FourierMLP
from image2sphere.nn.icosahedral import IcosahedralI2S
from image2sphere.nn.ipdf import IPDF
from image2sphere.nn.projector import HarmonicS2Projector, SpatialS2Projector
from image2sphere.nn.regression import RotationRegression
from image2sphere.nn.s2_conv import S2Conv
from image2sphere.nn.so3_conv import SO3Conv
from image2sphere.nn.so3_flow import RotationFlow
from image2sphere.nn.wigner_regression import WignerDRegression

__all__ = [
    "BinDeltaRegression",
    "BinghamNet",
    "EulerBinsNet",
    "ViewpointBinsNet",
    "MatrixFisherNet",
    "RotationLaplaceNet",
    "VonMisesNet",
    "I2S",
    "IcosahedralI2S",
    "IPDF",
    "PoseNetwork",
    "RotationFlow",
    "RotationRegression",
    "SphericalRegression",
    "RESNET_DEPTHS",
    "FourierMLP",
    "HarmonicS2Projector",
    "ResNetEncoder",
    "TorchvisionEncoder",
    "S2Conv",
    "SO3Conv",
    "SO3ReLU",
    "SpatialS2Projector",
    "WignerDRegression",
]
