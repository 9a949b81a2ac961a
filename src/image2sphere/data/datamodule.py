"""The base LightningDataModule of the datasets (:class:`PoseDataModule`): its loaders and worker settings.

Workers are persistent, images are decoded in them, each opens its own file handles
(:func:`~image2sphere.data.workers.init_worker`), they start from a fork server by default
(:func:`~image2sphere.data.workers.worker_context`), and memory is pinned only when a CUDA device is present.
"""

from __future__ import annotations

import logging

import lightning.pytorch as pl
import torch
from torch.utils.data import DataLoader

from image2sphere.data.loading import EpochShuffleSampler, PaddedDataset, ShardSampler, collate_skipping_corrupt
from image2sphere.data.workers import (
    AUTO,
    DEFAULT_START_METHOD,
    auto_num_workers,
    check_multiprocessing_context,
    check_num_workers,
    init_worker,
    local_processes,
    worker_context,
)

__all__ = ["PoseDataModule"]

log = logging.getLogger(__name__)


class PoseDataModule(pl.LightningDataModule):
    """The loaders shared by the dataset modules: a seeded per-epoch shuffle for training, the
    dataset order for evaluation, every image kept (no dropped last batch), corrupt images skipped
    by :func:`~image2sphere.data.loading.collate_skipping_corrupt`.

    Workers: ``num_workers`` is set as an integer or ``"auto"``
    (:func:`~image2sphere.data.workers.check_num_workers`) and read as the integer it resolves to
    (:func:`~image2sphere.data.workers.auto_num_workers` with
    :func:`~image2sphere.data.workers.local_processes` of the attached trainer). With workers they are
    persistent (started once per loader, not every epoch), images are decoded in them, and
    :func:`~image2sphere.data.workers.init_worker` runs in each. ``pin_memory`` applies only
    when a CUDA device is present. ``multiprocessing_context`` is how workers start: set as ``"fork"``,
    ``"forkserver"``, ``"spawn"`` or ``None``
    (:func:`~image2sphere.data.workers.check_multiprocessing_context`), read as the method it resolves to
    (``None``: :data:`~image2sphere.data.workers.DEFAULT_START_METHOD`, ``forkserver`` on Linux; ``fork``
    can deadlock a worker at start in a rank with threads, see :mod:`~image2sphere.data.workers`).

    Subclasses set ``data_train``, ``data_val`` (or ``None``), ``data_test`` in ``setup`` and
    ``batch_size``, ``num_workers``, ``multiprocessing_context``, ``pin_memory``, ``seed`` and
    ``class_names`` in ``__init__``.
    """

    _resume: tuple[int, int] | None = None
    _start_epoch: int = 0
    _num_workers: int | str = 0
    _multiprocessing_context: str | None = None

    @property
    def num_workers(self) -> int:
        """Loader workers per loader: the integer set, or what ``auto`` resolves to here."""
        if self._num_workers == AUTO:
            return auto_num_workers(processes=local_processes(getattr(self, "trainer", None)))
        return int(self._num_workers)

    @num_workers.setter
    def num_workers(self, value: int | str | None) -> None:
        self._num_workers = check_num_workers(value)

    @property
    def num_workers_setting(self) -> int | str:
        """``num_workers`` as configured: an integer or ``"auto"``."""
        return self._num_workers

    @property
    def multiprocessing_context(self) -> str:
        """How the workers start: the method set, or the default it resolves to (``forkserver`` on Linux)."""
        return self._multiprocessing_context or DEFAULT_START_METHOD

    @multiprocessing_context.setter
    def multiprocessing_context(self, value: str | None) -> None:
        self._multiprocessing_context = check_multiprocessing_context(value)

    def resume_within_epoch(self, epoch: int, batches_done: int) -> None:
        """Start training in ``epoch`` after its first ``batches_done`` batches (a checkpoint written
        mid-epoch, see :mod:`image2sphere.training.checkpointing`); later epochs are whole."""
        self._resume = (int(epoch), int(batches_done) * int(self.batch_size))

    def start_at_epoch(self, epoch: int) -> None:
        """The training sampler's epoch before Lightning first sets it: the epoch a resumed run starts in.

        Lightning creates the training iterator of a resumed run before it tells the sampler the epoch,
        and does not create it again for that first epoch; loader workers fetch their first indices as the
        iterator is created. Without this, a run resumed in epoch ``e > 0`` with ``num_workers > 0`` would
        train its first epoch on epoch 0's permutation and labels (measured: final weights 1.4 apart from
        the uninterrupted run's; with ``num_workers=0`` the indices are drawn later and were right)."""
        self._start_epoch = int(epoch)

    def _ranks(self) -> tuple[int, int]:
        """``(world size, global rank)`` of the run this module is attached to (``(1, 0)`` outside one)."""
        trainer = getattr(self, "trainer", None)
        if trainer is None or int(getattr(trainer, "world_size", 1)) <= 1:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    def _loader(self, dataset, train: bool) -> DataLoader:
        """A loader of ``dataset``: the seeded per-epoch permutation for training, the dataset's order for
        evaluation; in a distributed run each rank's share of either
        (:class:`~image2sphere.data.loading.EpochShuffleSampler`, :class:`~image2sphere.data.loading.ShardSampler`)."""
        world, rank = self._ranks()
        if train:
            sampler = EpochShuffleSampler(len(dataset), self.seed, dataset, self._resume, world, rank)
            if self._start_epoch:
                sampler.set_epoch(self._start_epoch)
        else:
            sampler = ShardSampler(len(dataset), world, rank) if world > 1 else None
            if sampler is not None:  # the same number of batches on every rank (empty slots at the end)
                dataset = PaddedDataset(dataset, sampler.total_size)
        workers = self.num_workers
        if self._num_workers == AUTO:
            log.info("dataset.num_workers=auto: %d loader workers", workers)
        return DataLoader(
            dataset,
            batch_size=self.batch_size,
            sampler=sampler,
            shuffle=False,
            drop_last=False,
            num_workers=workers,
            pin_memory=bool(self.pin_memory) and torch.cuda.is_available(),
            persistent_workers=workers > 0,
            worker_init_fn=init_worker if workers > 0 else None,
            multiprocessing_context=worker_context(self._multiprocessing_context) if workers > 0 else None,
            collate_fn=collate_skipping_corrupt,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, train=True)

    def val_dataloader(self) -> DataLoader | list:
        return self._loader(self.data_val, train=False) if self.data_val is not None else []

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_test, train=False)
