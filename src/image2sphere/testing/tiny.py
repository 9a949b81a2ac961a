"""The tiny settings of a test run: ``python -m src.train`` in seconds on a CPU (32 px images, lmax 2,
coarse grids, a narrow network). The tests' runs and the pre-emption stress check
(``benchmarks/preemption.py``) start from these overrides."""

from __future__ import annotations

__all__ = ["TINY"]

TINY = [
    "dataset.render.train=10",
    "dataset.render.test=3",
    "dataset.val_per_shape=2",
    "dataset.image_size=32",
    "dataset.batch_size=6",
    "lmax=2",
    "train_grid_level=2",
    "eval_grid_level=3",
    "model.spread_grid_level=2",
    "model.net.sphere_channels=16",
    "model.net.so3_channels=4",
    "model.net.activation_resolution=4",
    "trainer.accelerator=cpu",
    "trainer.num_sanity_val_steps=0",
]
