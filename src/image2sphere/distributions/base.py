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
    "CHUNK_POINTS",
    "LOG_UNIFORM_DENSITY",
    "DensityNotAvailable",
    "PointEstimate",
    "PoseDistribution",
    "check_threshold",
]
