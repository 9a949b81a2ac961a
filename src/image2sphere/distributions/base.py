"""The interface of every pose method's output (defined in :mod:`image2sphere.so3.pose_distribution`,
next to the grids it is scored on; re-exported here beside the families that implement it)."""

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
    """The number of components of a mixture family: a positive integer, else ``ValueError``."""
    if isinstance(num_components, bool) or not isinstance(num_components, int) or num_components < 1:
        raise ValueError(f"num_components must be a positive integer, got {num_components!r}")
    return num_components
