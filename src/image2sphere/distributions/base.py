"""The interface of every pose method's output (defined in :mod:`image2sphere.so3.pose_distribution`,
next to the grids it is scored on; re-exported here beside the families that implement it)."""

from image2sphere.checks import check_int
from image2sphere.so3.pose_distribution import (
    CHUNK_POINTS,
    LOG_UNIFORM_DENSITY,
    DensityNotAvailable,
    PointEstimate,
    PoseDistribution,
    check_threshold,
)

__all__ = [
    "check_num_components",
    "CHUNK_POINTS",
    "LOG_UNIFORM_DENSITY",
    "DensityNotAvailable",
    "PointEstimate",
    "PoseDistribution",
    "check_threshold",
]


def check_num_components(num_components) -> int:
    """The number of components of a mixture family: an integer >= 1, else ``ValueError``."""
    return check_int("num_components", num_components, 1)
