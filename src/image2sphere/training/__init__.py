"""Training and evaluation with Lightning, configured by Hydra (see ``conf/`` and ``src/train.py``)."""

from image2sphere.training.module import NonFiniteLossError, PoseEstimationModule
from image2sphere.training.pipeline import train
from image2sphere.training.resolvers import register_resolvers

__all__ = ["NonFiniteLossError", "PoseEstimationModule", "register_resolvers", "train"]
