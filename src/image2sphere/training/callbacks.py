"""Lightning callbacks of the training run: the ``callbacks`` config group (``conf/callbacks/``).

The checkpoint callback, :class:`~image2sphere.training.checkpoint.EpochCheckpoint`, is with the rest
of checkpointing; Hydra's callbacks, which run before the task, are :mod:`.hydra_callbacks`.
"""

from __future__ import annotations

import contextlib
import functools
import itertools
import logging
import math
import time
from collections.abc import Callable
from contextlib import AbstractContextManager
from pathlib import Path
from typing import Any

import lightning.pytorch as pl
import torch
from lightning.fabric.utilities.apply_func import move_data_to_device
from torch.optim.swa_utils import update_bn
from torch.utils.data import DataLoader

from image2sphere.checks import ConfigError, check_int
from image2sphere.data.loading import EpochShuffleSampler

__all__ = ["BatchNormStatistics", "NoteLoopStart", "SO3PlotCallback", "recompute_batchnorm_statistics"]

log = logging.getLogger(__name__)

#: training batches BatchNorm's statistics are averaged over when nothing says otherwise: the default of
#: :class:`BatchNormStatistics` and of ``src.eval``'s ``batchnorm_batches`` for a checkpoint whose run did not
#: name one (a run's config states its own: ``callbacks.batchnorm_statistics.num_batches``)
BATCHNORM_BATCHES = 50


class NoteLoopStart(pl.Callback):
    """Tells the entry point (:func:`image2sphere.training.entry.note_loop_start`) when a loop of the trainer
    starts (sanity check, training, validation, test, prediction): from then on the job's work has begun and
    its run directory is kept whatever ends it. Every trainer of ``src.train`` and ``src.eval`` has it."""

    def _started(self, *args: Any) -> None:
        from image2sphere.training.entry import note_loop_start

        note_loop_start()

    on_sanity_check_start = on_train_start = on_validation_start = on_test_start = on_predict_start = _started


class SO3PlotCallback(pl.Callback):
    """Plots the predicted distributions of a fixed set of validation images every few epochs.

    The first ``n_images`` validation images (the same ones every time) are drawn with
    :func:`image2sphere.plot.plot_so3_distribution` at grid ``level``, their ground truth as rings.
    PNGs go to ``<run dir>/plots/epoch=<e>_image=<i>.png`` (``epoch=<e>_step=<s>_image=<i>.png`` when
    ``trainer.val_check_interval`` is set, so that validations within an epoch keep their own files) and
    to the loggers that take images (wandb: ``val/so3_plot``; TensorBoard: a figure per image).

    Args:
        every_n_epochs: plot after the validation of every n-th epoch (and never in the sanity check).
        n_images: how many validation images.
        level: grid level of the plots (5 as in the paper; 4 is eight times cheaper).
        threshold: probability below which grid points are not drawn (``None``: ten times uniform).
    """

    def __init__(self, every_n_epochs: int = 5, n_images: int = 4, level: int = 4, threshold: float | None = None):
        if every_n_epochs < 1 or n_images < 0:
            raise ConfigError(
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
        stem = f"epoch={trainer.current_epoch:03d}"
        if trainer.val_check_interval != 1.0:  # validations within an epoch: each its own files (never overwritten)
            stem += f"_step={trainer.global_step:06d}"
        paths = []
        for i in range(min(self.n_images, len(dataset))):
            item = dataset[i]
            if item is None:
                continue
            title = f"epoch {trainer.current_epoch}, validation image {i}"
            fig = plot_dataset_item(pl_module, item, self.level, self.threshold, title, names)
            path = save_figure(fig, folder / f"{stem}_image={i}.png")
            paths.append(path)
            for logger in trainer.loggers:
                if type(logger).__name__ == "TensorBoardLogger":
                    logger.experiment.add_figure(f"val/so3_plot/{i}", fig, global_step=trainer.global_step)
        for logger in trainer.loggers:
            if type(logger).__name__ == "WandbLogger" and paths:
                logger.log_image(key="val/so3_plot", images=[str(p) for p in paths], step=trainer.global_step)
        log.info("plotted %d validation distributions into %s", len(paths), folder)


class BatchNormStatistics(pl.Callback):
    """Recomputes the running statistics of every BatchNorm layer from the current weights before each
    validation of a training run (and at the end of each training epoch whose weights they do not yet
    describe), so that evaluation, the checkpoint and ``src.predict`` normalise with statistics of the
    network as it is, not an exponential average over the weights of the last few hundred steps.

    Why: in training, BatchNorm normalises with the batch's own statistics; in evaluation with the
    running averages (momentum 0.1), which lag behind weights that are still moving. After a few
    hundred steps at a constant learning rate that lag can matter a great deal: on the renderer's marked
    sphere, where every image with the mark hidden is the same image, the running averages moved the
    network's mass off the rotations that hide the mark, which the same weights found with batch
    statistics (the figures: docs/training_fidelity.md, "Every SYMSOL shape").

    How: :func:`torch.optim.swa_utils.update_bn` (a cumulative average over the batches) on the first
    ``num_batches`` batches of this epoch's training order (at most the epoch's own number of batches),
    under the trainer's precision, with the global random state left as it was; in a distributed run each
    rank averages over its own share of that order and the ranks' statistics are then averaged (with
    ``trainer.sync_batchnorm`` the forward passes already share them). Training itself is unchanged:
    training batches are normalised with their own statistics, so the weights follow the same path
    with or without this callback; only evaluation sees a difference.

    Args:
        num_batches: how many training batches the statistics are averaged over (>= 1).
    """

    def __init__(self, num_batches: int = BATCHNORM_BATCHES):
        self.num_batches = check_int("callbacks.batchnorm_statistics.num_batches", num_batches, 1)
        self._done_at: int | None = None  # the global step whose weights the statistics describe
        self._warned = False

    def on_validation_epoch_start(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        if not trainer.sanity_checking and trainer.state.fn == "fit":
            self.recompute(trainer, pl_module)

    def on_train_epoch_end(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        self.recompute(trainer, pl_module)  # checkpoints are written after this hook (they run last)

    def recompute(self, trainer: pl.Trainer, pl_module: pl.LightningModule) -> None:
        """Recompute the statistics for the weights of ``trainer.global_step`` (once per step)."""
        if self._done_at == trainer.global_step:
            return
        loader = trainer.train_dataloader
        limit = trainer.num_training_batches
        if not (isinstance(loader, DataLoader) and loader.batch_size is not None):
            if not self._warned:
                log.warning(
                    "callbacks.batchnorm_statistics: the training loader is %s, not one DataLoader with a batch size; "
                    "BatchNorm's running averages are left as training kept them",
                    type(loader).__name__,
                )
                self._warned = True
        else:
            n = self.num_batches if math.isinf(limit) else min(self.num_batches, int(limit))
            recompute_batchnorm_statistics(
                pl_module, loader, n, trainer.current_epoch,
                forward=_BatchForward(pl_module, trainer.strategy.batch_to_device,
                                      trainer.precision_plugin.train_step_context),
                world_size=trainer.world_size, rank=trainer.global_rank,
                reduce=lambda t: trainer.strategy.reduce(t, reduce_op="mean"),
                device=trainer.strategy.root_device,
            )  # fmt: skip
        self._done_at = trainer.global_step


@torch.no_grad()
def recompute_batchnorm_statistics(
    module: torch.nn.Module,
    loader: DataLoader,
    num_batches: int,
    epoch: int = 0,
    forward: torch.nn.Module | None = None,
    world_size: int = 1,
    rank: int = 0,
    reduce: Callable[[torch.Tensor], torch.Tensor] | None = None,
    device: torch.device | None = None,
) -> int:
    """Replace the running statistics of every BatchNorm layer of ``module`` by their cumulative average
    (:func:`torch.optim.swa_utils.update_bn`) over the first ``num_batches`` batches of epoch ``epoch``'s
    training order (:class:`~image2sphere.data.loading.EpochShuffleSampler` with the seed of ``loader``'s
    sampler; this rank's share of it when ``world_size > 1``, the ranks' averages then averaged by
    ``reduce`` unless the layers are ``SyncBatchNorm``). ``loader`` gives the dataset, batch size, collate
    function and workers. ``forward``: a module that takes a batch (default: ``module(image, class_index)``
    on ``device``). The global random state and every module's train/eval mode are left as they were; a
    log line gives the layers, batches and time. Returns the number of layers recomputed."""
    norms = [m for m in module.modules() if isinstance(m, torch.nn.modules.batchnorm._BatchNorm)]
    if not norms or num_batches < 1:
        return 0
    seed = getattr(loader.sampler, "seed", 0)
    order = EpochShuffleSampler(len(loader.dataset), seed, loader.dataset, None, world_size, rank)
    order.epoch = int(epoch)  # not set_epoch: that would change the dataset's own epoch
    batches = DataLoader(
        loader.dataset,
        batch_size=loader.batch_size,
        sampler=list(itertools.islice(iter(order), num_batches * loader.batch_size)),
        num_workers=loader.num_workers,
        collate_fn=loader.collate_fn,
        worker_init_fn=loader.worker_init_fn,
        multiprocessing_context=loader.multiprocessing_context if loader.num_workers else None,
    )
    modes = {m: m.training for m in module.modules()}
    device = torch.device("cpu") if device is None else torch.device(device)
    if forward is None:
        forward = _BatchForward(module, functools.partial(move_data_to_device, device=device))
    start = time.perf_counter()
    with torch.random.fork_rng(devices=[device] if device.type == "cuda" else []):
        update_bn(batches, forward)
    for m, training in modes.items():
        m.train(training)
    if world_size > 1 and reduce is not None and not any(isinstance(m, torch.nn.SyncBatchNorm) for m in norms):
        for m in norms:
            for buf in (m.running_mean, m.running_var):
                if buf is not None:
                    buf.copy_(reduce(buf.clone()))
    log.info("BatchNorm statistics of %d layers recomputed over %d training batches (%.1f s)", len(norms),
             len(batches), time.perf_counter() - start)  # fmt: skip
    return len(norms)


class _BatchForward(torch.nn.Module):
    """``update_bn``'s model: a training batch (the dataset's dict, or ``None`` where every image was
    corrupt), moved by ``to_device``, through ``module(image, class_index)`` inside ``context()`` (in a
    fit: the trainer's strategy moves it, under the trainer's precision)."""

    def __init__(self, module: torch.nn.Module, to_device: Callable[[dict], dict],
                 context: Callable[[], AbstractContextManager] = contextlib.nullcontext):  # fmt: skip
        super().__init__()
        self.module, self.to_device, self.context = module, to_device, context

    def forward(self, batch: dict | None) -> None:
        if batch is not None:
            batch = self.to_device(batch)
            with self.context():
                self.module(batch["image"], batch.get("class_index"))
