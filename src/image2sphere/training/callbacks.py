"""Lightning callbacks of the training run: the ``callbacks`` config group (``conf/callbacks/``).

The checkpoint callback, :class:`~image2sphere.training.checkpoint.EpochCheckpoint`, is with the rest
of checkpointing; Hydra's callbacks, which run before the task, are :mod:`.hydra_callbacks`.
"""

from __future__ import annotations

import logging
from pathlib import Path

import lightning.pytorch as pl

__all__ = ["SO3PlotCallback"]

log = logging.getLogger(__name__)


class SO3PlotCallback(pl.Callback):
    """Plots the predicted distributions of a fixed set of validation images every few epochs.

    The first ``n_images`` validation images (the same ones every time) are drawn with
    :func:`image2sphere.plot.plot_so3_distribution` at grid ``level``, their ground truth as rings.
    PNGs go to ``<run dir>/plots/epoch=<e>_image=<i>.png`` and to the loggers that take images
    (wandb: ``val/so3_plot``; TensorBoard: a figure per image).

    Args:
        every_n_epochs: plot after the validation of every n-th epoch (and never in the sanity check).
        n_images: how many validation images.
        level: grid level of the plots (5 as in the paper; 4 is eight times cheaper).
        threshold: probability below which grid points are not drawn (``None``: ten times uniform).
    """

    def __init__(self, every_n_epochs: int = 5, n_images: int = 4, level: int = 4, threshold: float | None = None):
        if every_n_epochs < 1 or n_images < 0:
            raise ValueError(
                f"callbacks.so3_plot: every_n_epochs must be >= 1 and n_images >= 0, got {every_n_epochs}, {n_images}"
            )
        self.every_n_epochs = int(every_n_epochs)
        self.n_images = int(n_images)
        self.level = int(level)
        self.threshold = threshold

    def on_validation_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if trainer.sanity_checking or not trainer.is_global_zero or not self.n_images:
            return
        if (trainer.current_epoch + 1) % self.every_n_epochs:
            return
        dataset = getattr(trainer.datamodule, "data_val", None) if trainer.datamodule is not None else None
        if dataset is None or len(dataset) == 0:
            return
        from image2sphere.plot import plot_dataset_item, save_figure

        folder = Path(trainer.default_root_dir) / "plots"
        names = getattr(pl_module, "class_names", None) or []
        paths = []
        for i in range(min(self.n_images, len(dataset))):
            item = dataset[i]
            if item is None:
                continue
            title = f"epoch {trainer.current_epoch}, validation image {i}"
            fig = plot_dataset_item(pl_module, item, self.level, self.threshold, title, names)
            path = save_figure(fig, folder / f"epoch={trainer.current_epoch:03d}_image={i}.png")
            paths.append(path)
            for logger in trainer.loggers:
                if type(logger).__name__ == "TensorBoardLogger":
                    logger.experiment.add_figure(f"val/so3_plot/{i}", fig, global_step=trainer.global_step)
        for logger in trainer.loggers:
            if type(logger).__name__ == "WandbLogger" and paths:
                logger.log_image(key="val/so3_plot", images=[str(p) for p in paths], step=trainer.global_step)
        log.info("plotted %d validation distributions into %s", len(paths), folder)
