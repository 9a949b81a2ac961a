"""From dataset items to batches: the item format, epoch-dependent items, the samplers and collation.

Conventions
-----------
* Randomness in data loading is a function of ``(seed, epoch, index)`` only
  (:func:`~image2sphere.data.common.stable_seed`), never of a global random state, so a run resumed
  from a checkpoint sees the same batches as an uninterrupted one. A dataset whose items depend on
  the epoch (an :class:`EpochDataset`) gets the epoch with every training index (:class:`EpochIndex`,
  yielded by :class:`EpochShuffleSampler`), so the copy of the dataset in a persistent DataLoader
  worker, which never sees ``set_epoch``, follows it too.
* Evaluation shares the dataset order between the ranks of a distributed run (:class:`ShardSampler`), with
  empty slots (:data:`PADDING`) that give every rank the same number of batches.
* An item is a dict (:func:`single_label_item` for datasets with one label per image); a dataset that
  skips a corrupt image returns ``None``, which :func:`collate_skipping_corrupt` drops from its batch
  and counts in the batch's ``skipped`` entry.
"""

from __future__ import annotations

from collections.abc import Iterator, Sequence
from typing import NamedTuple

import numpy as np
import torch
from torch.utils.data import Dataset, DistributedSampler, default_collate

from image2sphere.checks import ConfigError
from image2sphere.data.common import normalize_images, stable_seed

__all__ = [
    "EpochDataset",
    "EpochIndex",
    "EpochShuffleSampler",
    "PADDING",
    "PaddedDataset",
    "ShardSampler",
    "collate_skipping_corrupt",
    "single_label_item",
]


def single_label_item(
    image: torch.Tensor, class_index: int, index: int, rotation: np.ndarray, return_all: bool
) -> dict[str, torch.Tensor]:
    """A dataset item with one rotation label: ``image`` uint8 ``(H, W, 3)`` normalised to ``(3, H, W)``,
    ``class_index``, ``index`` and ``rotation (3, 3)``, or for evaluation (``return_all``) the
    one-element set ``rotations (1, 3, 3)`` with ``mask (1,)``, the format of multi-label sets."""
    item = {
        "image": normalize_images(image),
        "class_index": torch.tensor(int(class_index), dtype=torch.int64),
        "index": torch.tensor(int(index), dtype=torch.int64),
    }
    rotation = torch.as_tensor(np.asarray(rotation, dtype=np.float32))
    if return_all:
        item["rotations"] = rotation[None]
        item["mask"] = torch.ones(1, dtype=torch.bool)
    else:
        item["rotation"] = rotation
    return item


def collate_skipping_corrupt(items: Sequence[dict | None]) -> dict | None:
    """Collate dataset items, dropping the ``None`` of skipped corrupt images and the :data:`PADDING` of
    empty slots (:class:`ShardSampler`).

    The batch gets ``skipped`` (int64 scalar): how many corrupt images were dropped. ``None`` when nothing
    is left and something was corrupt; :data:`PADDING` when the batch held empty slots only.
    """
    kept = [item for item in items if item is not None and item is not PADDING]
    skipped = sum(item is None for item in items)
    if not kept:
        return None if skipped else PADDING
    batch = default_collate(kept)
    batch["skipped"] = torch.tensor(skipped)
    return batch


# --------------------------------------------------------------------------------------------------
# Epoch-dependent items and the training sampler


class EpochIndex(NamedTuple):
    """A training index together with the epoch it is drawn in.

    :class:`EpochShuffleSampler` yields these for an :class:`EpochDataset`: the index reaches the
    dataset's copy in a DataLoader worker process with the epoch in it, so per-epoch randomness
    follows ``(seed, epoch, index)`` even in persistent workers, whose copies of the dataset never
    see a :meth:`~EpochDataset.set_epoch` called in the main process.
    """

    epoch: int
    index: int


class EpochDataset(Dataset):
    """A dataset whose items depend on the epoch (random label choices, augmentation, random draws).

    ``dataset[i]`` uses :attr:`epoch` (set with :meth:`set_epoch`); ``dataset[EpochIndex(e, i)]``
    uses ``e`` and leaves :attr:`epoch` alone. Subclasses read their key with :meth:`epoch_and_index`.
    """

    epoch: int = 0

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)

    def epoch_and_index(self, key: int | EpochIndex) -> tuple[int, int]:
        """``(epoch, index)`` of a key: an :class:`EpochIndex` (or any pair) or a plain index, which
        takes the epoch of the last :meth:`set_epoch`."""
        if isinstance(key, tuple):
            epoch, index = key
            return int(epoch), int(index)
        return self.epoch, int(key)


class EpochShuffleSampler(DistributedSampler):
    """A random permutation of ``range(n)`` that depends only on ``(seed, epoch)``, shared out between
    the ranks of a distributed run.

    Lightning calls :meth:`set_epoch` before every training epoch. For an :class:`EpochDataset` the
    sampler yields :class:`EpochIndex` ``(epoch, index)`` pairs, so the dataset's own per-item
    randomness follows the sampler's epoch in every process (DataLoader workers included, persistent
    or not, forked or spawned); other datasets get plain ``int`` indices. The dataset (if given) is
    also told the epoch in this process, for code that indexes it directly.

    With ``num_replicas > 1`` (data-parallel training), rank ``r`` takes every ``num_replicas``-th index
    of the epoch's permutation from the ``r``-th on; the permutation is first padded with its own
    first indices to a multiple of ``num_replicas``, so that every rank takes as many training steps
    (DDP needs that). A resumed epoch (``resume``: ``(epoch, k)``) leaves out the first ``k`` indices of
    each rank's share, the ones it trained on before the checkpoint. It is a ``DistributedSampler`` so
    that Lightning uses it as it is instead of wrapping it in its own, which would shuffle again.
    """

    def __init__(
        self,
        n: int,
        seed: int,
        dataset: object | None = None,
        resume: tuple[int, int] | None = None,
        num_replicas: int = 1,
        rank: int = 0,
    ):
        # DistributedSampler.__init__ is not called: it would ask torch.distributed for the ranks; the
        # attributes it sets (and readers of a DistributedSampler use) are set here
        self.n = int(n)
        self.seed = int(seed)
        self.epoch = 0
        self.dataset = dataset
        self.with_epoch = isinstance(dataset, EpochDataset)
        # (epoch, k): in that epoch, leave out the first k indices of this rank's share
        self.resume = resume
        self.num_replicas, self.rank = _check_rank(num_replicas, rank)
        self.shuffle, self.drop_last = True, False
        self.num_samples = -(-self.n // self.num_replicas)  # ceil
        self.total_size = self.num_samples * self.num_replicas

    def set_epoch(self, epoch: int) -> None:
        self.epoch = int(epoch)
        if self.dataset is not None and hasattr(self.dataset, "set_epoch"):
            self.dataset.set_epoch(epoch)

    def __iter__(self) -> Iterator[int] | Iterator[EpochIndex]:
        g = torch.Generator().manual_seed(stable_seed("shuffle", self.seed, self.epoch))
        order = torch.randperm(self.n, generator=g).tolist()
        if self.num_replicas > 1:
            order = (order + order[: self.total_size - self.n])[self.rank :: self.num_replicas]
        if self.resume is not None and self.resume[0] == self.epoch:
            order = order[self.resume[1] :]
        if self.with_epoch:
            return iter([EpochIndex(self.epoch, i) for i in order])
        return iter(order)

    def __len__(self) -> int:
        return self.num_samples


class ShardSampler(DistributedSampler):
    """The evaluation order ``range(n)`` shared out between ``num_replicas`` ranks, every image scored by
    exactly one rank, every rank given the same number of slots: rank ``r`` takes ``r, r + num_replicas,
    ...`` below ``ceil(n / num_replicas) * num_replicas``; the indices from ``n`` on are empty slots
    (:class:`PaddedDataset` gives :data:`PADDING` there, which :func:`collate_skipping_corrupt` drops).
    Equal shares give every rank the same number of batches, so that points passed once per batch (the
    ranks' stop decisions) match, and a rank never has no batch at all (Lightning would skip its test
    loop, and the others would wait for its part of the results). The test gathers the per-image results
    (``PoseEstimationModule``). A ``DistributedSampler`` so that Lightning keeps it (its own pads the
    shares with repeats)."""

    def __init__(self, n: int, num_replicas: int, rank: int):
        self.n = int(n)
        self.dataset = None
        self.epoch, self.seed, self.shuffle, self.drop_last = 0, 0, False, False
        self.num_replicas, self.rank = _check_rank(num_replicas, rank)
        self.num_samples = -(-self.n // self.num_replicas)  # ceil
        self.total_size = self.num_samples * self.num_replicas

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.rank, self.total_size, self.num_replicas))

    def __len__(self) -> int:
        return self.num_samples


class _Padding:
    """The item of an empty slot: one object, also after pickling (loader workers)."""

    _instance: _Padding | None = None

    def __new__(cls) -> _Padding:
        if cls._instance is None:
            cls._instance = super().__new__(cls)
        return cls._instance

    def __reduce__(self) -> tuple:
        return (_Padding, ())

    def __repr__(self) -> str:
        return "PADDING"


#: what :class:`PaddedDataset` gives for an empty slot, and :func:`collate_skipping_corrupt` for a batch of
#: empty slots only (a batch with nothing to score, not counted as skipped)
PADDING = _Padding()


class PaddedDataset(Dataset):
    """``dataset`` followed by empty slots (:data:`PADDING`) up to ``length`` items (the slots
    :class:`ShardSampler` gives the ranks with the smaller shares)."""

    def __init__(self, dataset: Dataset, length: int):
        if int(length) < len(dataset):
            raise ConfigError(f"length must be at least the dataset's {len(dataset)} items, got {length}")
        self.dataset, self.length = dataset, int(length)

    def __len__(self) -> int:
        return self.length

    def __getitem__(self, index: int):
        return self.dataset[index] if index < len(self.dataset) else PADDING

    def init_worker(self) -> None:
        """The wrapped dataset's start in a loader worker (:func:`~image2sphere.data.workers.init_worker`)."""
        init = getattr(self.dataset, "init_worker", None)
        if callable(init):
            init()


def _check_rank(num_replicas: int, rank: int) -> tuple[int, int]:
    if int(num_replicas) < 1 or not 0 <= int(rank) < int(num_replicas):
        raise ConfigError(
            f"rank must lie in [0, num_replicas) and num_replicas >= 1, got rank {rank} of {num_replicas}"
        )
    return int(num_replicas), int(rank)
