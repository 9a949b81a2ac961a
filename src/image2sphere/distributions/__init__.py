"""Distributions over SO(3), the only home of them.

* :mod:`~image2sphere.distributions.base`: the interface every pose method's output goes through
  (:class:`~image2sphere.distributions.base.PoseDistribution`, its contract) and
  :class:`~image2sphere.distributions.base.PointEstimate` (a point regressor's output).
* :mod:`~image2sphere.distributions.grid_protocol`: how every family is scored on the HEALPix grid
  (streamed sweeps, log densities, modes, sampling, points above a threshold), for any family;
  :mod:`~image2sphere.distributions.hdr_masses`: the highest-density-region masses of its sweep.
* The families, one module each: ``fourier`` (I2S's :class:`~image2sphere.distributions.fourier.SO3Distribution`),
  ``matrix_fisher``, ``rotation_laplace``, ``bingham``, ``von_mises``, ``euler_bins``, ``implicit``,
  ``flow`` (a normalizing flow's exact density and samples).
"""

from image2sphere.distributions.base import (
    LOG_UNIFORM_DENSITY,
    DensityNotAvailable,
    PointEstimate,
    PoseDistribution,
    check_threshold,
)
from image2sphere.distributions.fourier import SO3Distribution

__all__ = [
    "LOG_UNIFORM_DENSITY",
    "DensityNotAvailable",
    "PointEstimate",
    "PoseDistribution",
    "SO3Distribution",
    "check_threshold",
]
