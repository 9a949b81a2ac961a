"""Pieces shared by the datasets: image loading and normalisation, seeded shuffling, collation,
corrupt-image handling, missing-dataset messages and the report of the ``verify`` commands.

Conventions
-----------
* Images reach the network as float32 ``(3, H, W)``, normalised with the ImageNet mean and
  standard deviation (what torchvision's ResNet weights expect).
* Randomness in data loading is a function of ``(seed, epoch, index)`` only, never of a global
  random state, so a run resumed from a checkpoint sees the same batches as an uninterrupted one.
  A dataset whose items depend on the epoch (an :class:`EpochDataset`) gets the epoch with every
  training index (:class:`EpochIndex`, yielded by :class:`EpochShuffleSampler`), so the copy of the
  dataset in a persistent DataLoader worker, which never sees ``set_epoch``, follows it too.
* Loaders (:class:`PoseDataModule`): ``dataset.num_workers`` is an integer or ``auto``
  (:func:`auto_num_workers`); workers are persistent, images are decoded in them, each opens its own
  file handles (:func:`init_worker`), and memory is pinned only when a CUDA device is present.
* A corrupt image inside a dataset raises :class:`CorruptImageError` naming the file (or LMDB key),
  or, with ``on_corrupt="skip"``, is logged, dropped from its batch by :func:`collate_skipping_corrupt`
  and counted in the batch's ``skipped`` entry.
"""

from __future__ import annotations

import hashlib
import io
import logging
import os
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import NamedTuple

import lightning.pytorch as pl
import numpy as np
import torch
from PIL import Image, UnidentifiedImageError
from torch.utils.data import DataLoader, Dataset, DistributedSampler, default_collate, get_worker_info

__all__ = [
    "AUTO_WORKERS_CAP",
    "CORRUPT_POLICIES",
    "IMAGENET_MEAN",
    "IMAGENET_STD",
    "CorruptImageError",
    "DatasetNotFoundError",
    "EpochDataset",
    "EpochIndex",
    "EpochShuffleSampler",
    "ShardSampler",
    "PoseDataModule",
    "VerifyReport",
    "auto_num_workers",
    "available_cpus",
    "check_corrupt_policy",
    "check_num_workers",
    "collate_skipping_corrupt",
    "decode_image",
    "image_to_uint8",
    "init_worker",
    "load_image",
    "local_processes",
    "missing_dataset_error",
    "single_label_item",
    "skip_corrupt",
    "normalize_images",
    "stable_seed",
]

log = logging.getLogger(__name__)

CORRUPT_POLICIES = ("fail", "skip")


class CorruptImageError(ValueError):
    """An image file (or LMDB record) that cannot be decoded; ``source`` names it."""

    def __init__(self, source: str, reason: str):
        self.source = source
        super().__init__(f"cannot decode image {source} ({reason}); the file is corrupt or truncated: re-download it")


class DatasetNotFoundError(FileNotFoundError):
    """A dataset is not where the configuration says (see :func:`missing_dataset_error`)."""


def missing_dataset_error(
    name: str, looked_at: Path, expected: str, get_from: str, key: str, docs: str | None = None
) -> DatasetNotFoundError:
    """The error for a dataset that is missing or incomplete: where we looked, what should be there,
    where to get it, which config key points at it and (``docs``) where the layout is described."""
    see = f" (the layout is described in {docs})" if docs else ""
    return DatasetNotFoundError(
        f"{name} not found at {looked_at}: expected {expected}. Get it from {get_from} and unpack it there, "
        f"or point {key} at your copy{see}"
    )


def check_corrupt_policy(value: str, key: str) -> str:
    if value not in CORRUPT_POLICIES:
        raise ValueError(f"{key} must be one of {CORRUPT_POLICIES}, got {value!r}")
    return value


IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def stable_seed(*parts: object) -> int:
    """A 63-bit seed from any printable parts, identical across processes and Python versions."""
    digest = hashlib.sha256("/".join(map(str, parts)).encode()).digest()
    return int.from_bytes(digest[:8], "little") >> 1


class _UnreadablePixels(ValueError):
    """Pixels that decode but cannot be read as an 8-bit image (e.g. a float image outside [0, 1])."""


_HIGH_DEPTH_MODES = ("I;16", "I;16L", "I;16B", "I;16N", "I", "F")
_ALPHA_MODES = ("RGBA", "LA", "PA", "RGBa", "La")
_transparency_reported = False


def _gray_to_uint8(image: Image.Image, name: str) -> tuple[np.ndarray, np.ndarray | None]:
    """A 16-bit, 32-bit integer or float grayscale image as 8-bit gray ``(H, W)``, and an alpha
    ``(H, W)`` when a ``transparency`` value marks pixels as transparent (else ``None``).

    16-bit samples (``I;16*``, and ``I``, which is how Pillow gives 16-bit PNG and TIFF samples) are
    divided by 257 (65535 -> 255); float (``F``) samples are intensities in ``[0, 1]``.
    """
    x = np.asarray(image)
    if image.mode == "F":
        x = x.astype(np.float64)
        if x.size and not (np.isfinite(x).all() and x.min() >= 0.0 and x.max() <= 1.0):
            low, high = (float(np.nanmin(x)), float(np.nanmax(x))) if np.isfinite(x).any() else (np.nan, np.nan)
            raise _UnreadablePixels(
                f"image {name} is a float image with values in [{low:g}, {high:g}] (or not finite); float images are "
                "read as intensities in [0, 1]: convert it to 8 or 16 bits, or scale it to [0, 1]"
            )
        gray = np.rint(x * 255.0)
    else:
        x = x.astype(np.int64)
        if x.size and (x.min() < 0 or x.max() > 65535):
            raise _UnreadablePixels(
                f"image {name} is a 32-bit integer image with values in [{x.min()}, {x.max()}]; integer images "
                "are read as 16-bit samples (0..65535): convert it to 8 or 16 bits"
            )
        gray = (x + 128) // 257  # round(x / 257)
    key = image.info.get("transparency")
    alpha = np.where(x == key, 0, 255).astype(np.uint8) if isinstance(key, (int, float)) else None
    return gray.astype(np.uint8), alpha


def _to_rgb(image: Image.Image, name: str) -> Image.Image:
    """``image`` as 8-bit RGB by the rules of :func:`decode_image` (loads every pixel)."""
    global _transparency_reported
    alpha = None
    if image.mode in _HIGH_DEPTH_MODES:
        gray, alpha = _gray_to_uint8(image, name)
        rgb = np.repeat(gray[..., None], 3, axis=-1)
    elif image.mode in _ALPHA_MODES or "transparency" in image.info:
        rgba = np.asarray(image.convert("RGBA"))
        rgb, alpha = rgba[..., :3], rgba[..., 3]
    elif image.mode == "RGB":
        return image.copy()  # a copy: the caller may close the file behind ``image``
    else:
        return image.convert("RGB")
    if alpha is not None and (alpha < 255).any():
        # composite onto black: out = rgb * alpha / 255, rounded
        rgb = ((rgb.astype(np.uint32) * alpha[..., None].astype(np.uint32) + 127) // 255).astype(np.uint8)
        if not _transparency_reported:
            _transparency_reported = True
            log.warning(
                "image %s has transparent pixels: composited onto black, the background of the rendered "
                "training images (reported once; later images are composited the same way)",
                name,
            )
    return Image.fromarray(np.ascontiguousarray(rgb, dtype=np.uint8))


def decode_image(source: str | Path | bytes, name: str | None = None) -> Image.Image:
    """A fully decoded 8-bit RGB :class:`PIL.Image.Image` from a file path or encoded bytes.

    Conversion rules (shared by datasets and prediction, see :func:`image_to_uint8`):

    * grayscale and palette images become three equal channels;
    * 16-bit samples (modes ``I;16*``, and ``I``, Pillow's mode for 16-bit PNG and TIFF) are scaled to
      8 bits (divided by 257); ``I`` values outside ``0..65535`` are refused; float (``F``) samples
      are intensities in ``[0, 1]`` (anything else is refused);
    * transparency (an alpha channel: ``RGBA``, ``LA``, ``PA``; or a ``transparency`` colour, e.g. of
      palette images) is composited onto a **black** background, ``rgb * alpha / 255``: the
      background of the rendered training images (:mod:`image2sphere.data.render`). A warning is
      logged the first time an image with transparent pixels is met.

    Raises ``FileNotFoundError`` for a missing file, :class:`CorruptImageError` naming ``name``
    (default: the path) for anything that does not decode completely, truncated files included, and
    ``ValueError`` naming it for pixel values the rules above refuse.
    """
    name = name or (f"({len(source)} bytes in memory)" if isinstance(source, bytes) else str(source))
    try:
        with Image.open(io.BytesIO(source) if isinstance(source, bytes) else Path(source)) as im:
            im.load()  # every pixel, so truncation is detected here
            return _to_rgb(im, name)
    except FileNotFoundError:
        raise FileNotFoundError(f"image file not found: {name}") from None
    except _UnreadablePixels as e:
        raise ValueError(str(e)) from None
    except (UnidentifiedImageError, OSError, SyntaxError, ValueError) as e:
        raise CorruptImageError(name, str(e)) from e


def load_image(source: str | Path | bytes, image_size: int | None = None, name: str | None = None) -> torch.Tensor:
    """An image (file path or encoded bytes) as uint8 RGB ``(H, W, 3)``, resized (bilinear,
    antialiased) to a square ``image_size`` when given. Conversion and errors as :func:`decode_image`.
    """
    return image_to_uint8(decode_image(source, name), image_size)


def image_to_uint8(image: Image.Image, image_size: int | None = None, name: str | None = None) -> torch.Tensor:
    """A PIL image as uint8 RGB ``(H, W, 3)``, resized (bilinear, antialiased) to a square ``image_size``.

    Any mode is converted by the rules of :func:`decode_image` (16-bit and float scaling,
    transparency composited onto black); ``name`` names the image in messages.
    """
    if image.mode != "RGB" or "transparency" in image.info:
        try:
            image = _to_rgb(image, name or "(in memory)")
        except _UnreadablePixels as e:
            raise ValueError(str(e)) from None
    if image_size is not None and image.size != (image_size, image_size):
        image = image.resize((image_size, image_size), Image.Resampling.BILINEAR, reducing_gap=None)
    return torch.from_numpy(np.asarray(image, dtype=np.uint8).copy())


def skip_corrupt(error: CorruptImageError, policy: str, warned: set[str]) -> None:
    """Apply ``dataset.on_corrupt`` to a corrupt image: re-raise on ``"fail"``; on ``"skip"`` log it
    (once per image; ``warned`` remembers which) and return, the caller's item being ``None``."""
    if policy == "fail":
        raise error
    if error.source not in warned:
        warned.add(error.source)
        log.warning("skipping corrupt image %s (dataset.on_corrupt=skip)", error.source)


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
    """Collate dataset items, dropping the ``None`` of skipped corrupt images.

    The batch gets ``skipped`` (int64 scalar): how many were dropped. ``None`` when all were.
    """
    kept = [item for item in items if item is not None]
    if not kept:
        return None
    batch = default_collate(kept)
    batch["skipped"] = torch.tensor(len(items) - len(kept))
    return batch


@dataclass
class VerifyReport:
    """What a dataset's ``verify`` found: counts per (split, class) against the expected ones,
    files that do not decode, and other problems (missing files, bad labels)."""

    dataset: str
    root: Path
    counts: list[tuple[str, str, int, int | None]] = field(default_factory=list)  # split, class, found, expected
    unreadable: list[str] = field(default_factory=list)
    problems: list[str] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def count(self, split: str, name: str, found: int, expected: int | None = None) -> None:
        self.counts.append((split, name, int(found), None if expected is None else int(expected)))

    @property
    def mismatches(self) -> list[tuple[str, str, int, int | None]]:
        return [c for c in self.counts if c[3] is not None and c[2] != c[3]]

    @property
    def ok(self) -> bool:
        return not (self.unreadable or self.problems or self.mismatches)

    def decode_files(self, paths, desc: str, progress: bool = True) -> None:
        """Decode every image file of ``paths`` completely (progress bar ``desc``); the ones that do
        not decode are added to :attr:`unreadable`."""
        from tqdm import tqdm

        for path in tqdm(paths, desc=desc, disable=not progress):
            try:
                decode_image(path)
            except CorruptImageError:
                self.unreadable.append(str(path))

    def format(self, max_listed: int = 20) -> str:
        lines = [f"{self.dataset} at {self.root}"]
        if self.counts:
            width = max(len(f"{s}/{c}") for s, c, _, _ in self.counts)
            lines.append(f"  {'split/class':<{width}} {'found':>8} {'expected':>9}")
            for split, name, found, expected in self.counts:
                flag = "" if expected is None or found == expected else "  <-- mismatch"
                exp = "-" if expected is None else str(expected)
                lines.append(f"  {f'{split}/{name}':<{width}} {found:>8} {exp:>9}{flag}")
        for title, items in (("unreadable files", self.unreadable), ("problems", self.problems)):
            if items:
                lines.append(f"  {len(items)} {title}:")
                lines += [f"    {item}" for item in items[:max_listed]]
                if len(items) > max_listed:
                    lines.append(f"    ... and {len(items) - max_listed} more")
        lines += [f"  note: {n}" for n in self.notes]
        lines.append("  OK" if self.ok else "  FAILED")
        return "\n".join(lines)


def normalize_images(images: torch.Tensor) -> torch.Tensor:
    """uint8 ``(..., H, W, 3)`` -> float32 ``(..., 3, H, W)`` with ImageNet normalisation."""
    x = images.movedim(-1, -3).to(torch.float32) / 255.0
    mean = torch.tensor(IMAGENET_MEAN, dtype=x.dtype)[:, None, None]
    std = torch.tensor(IMAGENET_STD, dtype=x.dtype)[:, None, None]
    return (x - mean) / std


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
    """The evaluation order ``range(n)`` shared out between ``num_replicas`` ranks without repeats: rank
    ``r`` takes ``r, r + num_replicas, ...`` (shares differ by at most one image). Every image is scored by
    exactly one rank; the test gathers the per-image results (``PoseEstimationModule``). A
    ``DistributedSampler`` so that Lightning keeps it (its own pads the shares with repeats)."""

    def __init__(self, n: int, num_replicas: int, rank: int):
        self.n = int(n)
        self.dataset = None
        self.epoch, self.seed, self.shuffle, self.drop_last = 0, 0, False, False
        self.num_replicas, self.rank = _check_rank(num_replicas, rank)
        self.num_samples = len(range(self.rank, self.n, self.num_replicas))
        self.total_size = self.n

    def __iter__(self) -> Iterator[int]:
        return iter(range(self.rank, self.n, self.num_replicas))

    def __len__(self) -> int:
        return self.num_samples


def _check_rank(num_replicas: int, rank: int) -> tuple[int, int]:
    if int(num_replicas) < 1 or not 0 <= int(rank) < int(num_replicas):
        raise ValueError(f"rank must lie in [0, num_replicas) and num_replicas >= 1, got rank {rank} of {num_replicas}")
    return int(num_replicas), int(rank)


# --------------------------------------------------------------------------------------------------
# Workers


AUTO_WORKERS_CAP = 8
_AUTO = "auto"


def available_cpus() -> int:
    """CPUs this process may run on (its affinity mask; ``os.cpu_count()`` where there is none)."""
    try:
        return len(os.sched_getaffinity(0))
    except AttributeError:  # not on Linux
        return os.cpu_count() or 1


def local_processes(trainer: object | None = None) -> int:
    """Training processes on this machine, each of which starts its own loader workers.

    ``LOCAL_WORLD_SIZE`` when set (torchrun and torch.distributed launchers set it), else the number
    of devices of a Lightning ``trainer`` (one process per device under DDP), else 1.
    """
    value = os.environ.get("LOCAL_WORLD_SIZE", "")
    if value.strip().isdigit() and int(value) > 0:
        return int(value)
    devices = getattr(trainer, "num_devices", None) if trainer is not None else None
    if isinstance(devices, int) and not isinstance(devices, bool) and devices > 0:
        return devices
    return 1


def auto_num_workers(cpus: int | None = None, processes: int | None = None) -> int:
    """What ``num_workers: auto`` resolves to: ``min(8, cpus // processes - 1)``, at least 0.

    ``cpus``: :func:`available_cpus`; ``processes``: training processes on this machine
    (:func:`local_processes`). One CPU per process is left to the training loop itself; beyond 8
    workers a loader rarely gets faster and every worker holds a copy of the dataset's index.
    """
    cpus = available_cpus() if cpus is None else int(cpus)
    processes = 1 if processes is None else max(1, int(processes))
    return max(0, min(AUTO_WORKERS_CAP, cpus // processes - 1))


def check_num_workers(value: object, key: str = "dataset.num_workers") -> int | str:
    """A valid ``num_workers`` setting: an integer >= 0, or ``"auto"`` (``None`` means ``"auto"``);
    ``ValueError`` naming ``key`` for anything else."""
    if value is None or (isinstance(value, str) and value.strip().lower() == _AUTO):
        return _AUTO
    if isinstance(value, bool) or not isinstance(value, int) or value < 0:
        raise ValueError(
            f"{key} must be an integer >= 0 or auto (null means auto: min({AUTO_WORKERS_CAP}, CPUs // local "
            f"training processes - 1)), got {value!r}"
        )
    return int(value)


def init_worker(worker_id: int) -> None:
    """The DataLoader ``worker_init_fn`` of :class:`PoseDataModule`: calls ``init_worker()`` on the
    worker's copy of the dataset when it has one (the ModelNet10-SO(3) reader closes the LMDB
    environments inherited through ``fork`` there; each worker opens its own on first read)."""
    info = get_worker_info()
    init = getattr(info.dataset, "init_worker", None) if info is not None else None
    if callable(init):
        init()


# --------------------------------------------------------------------------------------------------
# DataModule


class PoseDataModule(pl.LightningDataModule):
    """The loaders shared by the dataset modules: a seeded per-epoch shuffle for training, the
    dataset order for evaluation, every image kept (no dropped last batch), corrupt images skipped
    by :func:`collate_skipping_corrupt`.

    Workers: ``num_workers`` is set as an integer or ``"auto"`` (:func:`check_num_workers`) and read
    as the integer it resolves to (:func:`auto_num_workers` with :func:`local_processes` of the
    attached trainer). With workers they are persistent (started once per loader, not every epoch),
    images are decoded in them, and :func:`init_worker` runs in each. ``pin_memory`` applies only
    when a CUDA device is present. ``multiprocessing_context`` (``None``: the platform's default,
    ``fork`` on Linux; or ``"spawn"``, ``"forkserver"``) is how workers start.

    Subclasses set ``data_train``, ``data_val`` (or ``None``), ``data_test`` in ``setup`` and
    ``batch_size``, ``num_workers``, ``pin_memory``, ``seed`` and ``class_names`` in ``__init__``.
    """

    _resume: tuple[int, int] | None = None
    _num_workers: int | str = 0
    multiprocessing_context: str | None = None

    @property
    def num_workers(self) -> int:
        """Loader workers per loader: the integer set, or what ``auto`` resolves to here."""
        if self._num_workers == _AUTO:
            return auto_num_workers(processes=local_processes(getattr(self, "trainer", None)))
        return int(self._num_workers)

    @num_workers.setter
    def num_workers(self, value: int | str | None) -> None:
        self._num_workers = check_num_workers(value)

    @property
    def num_workers_setting(self) -> int | str:
        """``num_workers`` as configured: an integer or ``"auto"``."""
        return self._num_workers

    def resume_within_epoch(self, epoch: int, batches_done: int) -> None:
        """Start training in ``epoch`` after its first ``batches_done`` batches (a checkpoint written
        mid-epoch, see :mod:`image2sphere.training.checkpointing`); later epochs are whole."""
        self._resume = (int(epoch), int(batches_done) * int(self.batch_size))

    def _ranks(self) -> tuple[int, int]:
        """``(world size, global rank)`` of the run this module is attached to (``(1, 0)`` outside one)."""
        trainer = getattr(self, "trainer", None)
        if trainer is None or int(getattr(trainer, "world_size", 1)) <= 1:
            return 1, 0
        return int(trainer.world_size), int(trainer.global_rank)

    def _loader(self, dataset, train: bool) -> DataLoader:
        """A loader of ``dataset``: the seeded per-epoch permutation for training, the dataset's order for
        evaluation; in a distributed run each rank's share of either (:class:`EpochShuffleSampler`,
        :class:`ShardSampler`)."""
        world, rank = self._ranks()
        if train:
            sampler = EpochShuffleSampler(len(dataset), self.seed, dataset, self._resume, world, rank)
        else:
            sampler = ShardSampler(len(dataset), world, rank) if world > 1 else None
        workers = self.num_workers
        if self._num_workers == _AUTO:
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
            multiprocessing_context=self.multiprocessing_context if workers > 0 else None,
            collate_fn=collate_skipping_corrupt,
        )

    def train_dataloader(self) -> DataLoader:
        return self._loader(self.data_train, train=True)

    def val_dataloader(self) -> DataLoader | list:
        return self._loader(self.data_val, train=False) if self.data_val is not None else []

    def test_dataloader(self) -> DataLoader:
        return self._loader(self.data_test, train=False)
