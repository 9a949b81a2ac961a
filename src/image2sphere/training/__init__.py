"""Training and evaluation with Lightning, configured by Hydra (see ``conf/`` and ``src/train.py``)."""

from image2sphere.training.module import NonFiniteLossError, PoseEstimationModule
from image2sphere.training.pipeline import format_metrics_table, register_resolvers, train

__all__ = ["NonFiniteLossError", "PoseEstimationModule", "format_metrics_table", "register_resolvers", "train"]
