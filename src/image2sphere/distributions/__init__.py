"""Distributions over SO(3): the interface every pose method's output goes through
(:class:`~image2sphere.distributions.base.PoseDistribution`) and the parametric families of the
baselines, one module each (``matrix_fisher``, ``rotation_laplace``, ``bingham``, ``von_mises``,
``implicit``). The Fourier family of I2S is :class:`image2sphere.so3.SO3Distribution`."""

from image2sphere.distributions.base import (
    LOG_UNIFORM_DENSITY,
    DensityNotAvailable,
    PointEstimate,
    PoseDistribution,
    check_threshold,
)

__all__ = ["LOG_UNIFORM_DENSITY", "DensityNotAvailable", "PointEstimate", "PoseDistribution", "check_threshold"]
