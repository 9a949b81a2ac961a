"""Kept for old configs only: the checkpoint module is :mod:`image2sphere.training.checkpoint`."""

# Every checkpoint and run directory written before the merge stores these classes' old dotted paths as
# ``_target_`` (callbacks.model_checkpoint, trainer.plugins in run_config and .hydra/config.yaml).
from image2sphere.training.checkpoint import AtomicCheckpointIO, EpochCheckpoint  # noqa: F401
