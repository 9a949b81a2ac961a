"""PASCAL3D+ (release 1.1) with RenderForCNN synthetic images: the Dataset (warping, augmentation, the
synthetic mix); the DataModule is in :mod:`image2sphere.data.datamodule`.

The layouts, annotations, object selection and camera conventions are in
:mod:`image2sphere.data.pascal3d_annotations` (docs/datasets.md#pascal3d-layout).

Protocol
--------
* Every image (train and test) is the box warped to ``image_size`` by turning a virtual camera
  toward the box centre (:func:`image2sphere.data.augment.box_to_virtual_camera`); the label is
  turned with it, so it stays exact. Training augmentation: horizontal flip (label ``F R F``, the
  categories being left-right symmetric about their ``x = 0`` plane), box edges jittered by up to
  ``box_jitter`` of the box size and a random roll of the virtual camera (``roll_std_deg``): the
  "slight random perspective change". Synthetic images use the whole image as the box and a long
  focal length (``synthetic_focal``), as their intrinsics are not published.
* Training mixes ``synthetic_ratio`` synthetic images per real image (3 in the paper): an epoch is
  every real image once plus ``round(synthetic_ratio * n_real)`` synthetic ones drawn at random.
* Randomness (flip, jitter, roll, synthetic draws) is a function of ``(seed, epoch, index)``.

Items: as :mod:`image2sphere.data.symsol`: ``image``, ``class_index``, ``index`` and ``rotation``
(training) or ``rotations (1, 3, 3)`` with ``mask (1,)`` (evaluation).
"""

from __future__ import annotations

import logging
import math
import os
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch
from PIL import ImageOps

from image2sphere.checks import ConfigError, check_number
from image2sphere.data.augment import GL_TO_CV, box_to_virtual_camera, hflip_box, hflip_rotation, warp_image
from image2sphere.data.common import (
    CorruptImageError,
    check_corrupt_policy,
    decode_image,
    skip_corrupt,
    stable_seed,
)
from image2sphere.data.loading import EpochDataset, EpochIndex, single_label_item
from image2sphere.data.pascal3d_annotations import (
    Pascal3DObject,
    SyntheticView,
)

__all__ = ["DEFAULT_AUGMENT", "Pascal3DDataset", "SyntheticViews", "check_augment"]

log = logging.getLogger(__name__)

DEFAULT_AUGMENT = {"flip": True, "box_jitter": 0.1, "roll_std_deg": 7.6}


# --------------------------------------------------------------------------------------------------
# Dataset
# --------------------------------------------------------------------------------------------------


class SyntheticViews(Sequence[SyntheticView]):
    """RenderForCNN views (:class:`~image2sphere.data.pascal3d_annotations.SyntheticView`) held as four
    tensors: the paths' bytes end to end, their offsets, the class indices and the angles.

    ``views[k]`` is the ``k``-th view. A list of view objects pickles to about 150 bytes per view and takes
    about 11 µs per view to unpickle (measured on 200,000): with RenderForCNN's hundreds of thousands of
    images, seconds for every loader worker started with ``forkserver`` or ``spawn``, which receive the
    dataset pickled, and a copy of every object in each of them. Tensors pickle to such a worker as shared
    memory (torch's multiprocessing reductions): nothing is copied per worker.
    """

    def __init__(self, views: Sequence[SyntheticView] = ()):
        paths = [os.fsencode(v.path) for v in views]
        offsets = np.zeros(len(paths) + 1, dtype=np.int64)
        np.cumsum([len(p) for p in paths], out=offsets[1:])
        joined = bytearray(b"".join(paths))
        self._paths = torch.frombuffer(joined, dtype=torch.uint8) if joined else torch.zeros(0, dtype=torch.uint8)
        self._offsets = torch.from_numpy(offsets)
        self._class_index = torch.tensor([v.class_index for v in views], dtype=torch.int64)
        angles = [(v.azimuth, v.elevation, v.tilt) for v in views]
        self._angles = torch.tensor(angles, dtype=torch.float64).reshape(len(angles), 3)

    def __len__(self) -> int:
        return len(self._class_index)

    def __getitem__(self, k):
        if isinstance(k, slice):
            return [self[j] for j in range(*k.indices(len(self)))]
        k = int(k)
        if not -len(self) <= k < len(self):
            raise IndexError(f"synthetic view {k} of {len(self)}")
        k %= len(self)
        start, end = int(self._offsets[k]), int(self._offsets[k + 1])
        path = Path(os.fsdecode(self._paths[start:end].numpy().tobytes()))
        azimuth, elevation, tilt = self._angles[k].tolist()
        return SyntheticView(path, int(self._class_index[k]), azimuth, elevation, tilt)


class Pascal3DDataset(EpochDataset):
    """Warped PASCAL3D+ objects, optionally augmented and mixed with RenderForCNN images.

    Items, :meth:`source` and :meth:`sample` take an index ``i`` (in the epoch of the last
    :meth:`set_epoch`) or an :class:`~image2sphere.data.loading.EpochIndex` ``(epoch, i)``, what the
    training sampler yields so that DataLoader workers follow the epoch.

    Args:
        real: the objects (:func:`~image2sphere.data.pascal3d_annotations.list_pascal3d_objects`).
        synthetic: RenderForCNN views to mix in (``None``: none); kept as :class:`SyntheticViews`.
        synthetic_ratio: synthetic images per real image in an epoch.
        augment: ``{"flip": bool, "box_jitter": float, "roll_std_deg": float}``; ``None``: no
            augmentation (evaluation).
        image_size: side of the warped images.
        return_all: evaluation items (``rotations (1, 3, 3)`` + ``mask``) instead of ``rotation``.
        on_corrupt: ``"fail"`` or ``"skip"`` (see :mod:`image2sphere.data.common`).
        seed: seed of the augmentation and of the synthetic draws.
        synthetic_focal: focal length (pixels) assumed for synthetic images.
    """

    def __init__(
        self,
        real: Sequence[Pascal3DObject],
        synthetic: Sequence[SyntheticView] | None = None,
        synthetic_ratio: float = 3.0,
        augment: dict | None = None,
        image_size: int = 224,
        return_all: bool = False,
        on_corrupt: str = "fail",
        seed: int = 0,
        synthetic_focal: float = 3000.0,
    ):
        self.real = list(real)
        self.synthetic = SyntheticViews(synthetic or ())  # a Sequence[SyntheticView] that pickles cheaply
        check_number("dataset.synthetic_ratio", synthetic_ratio, 0.0)
        self.n_synthetic = round(float(synthetic_ratio) * len(self.real)) if self.synthetic else 0
        self.augment = check_augment(augment)
        self.image_size = int(image_size)
        self.return_all = bool(return_all)
        self.on_corrupt = check_corrupt_policy(on_corrupt, "dataset.on_corrupt")
        self.seed = int(seed)
        self.synthetic_focal = float(synthetic_focal)
        self.epoch = 0
        self._warned: set[str] = set()

    def __len__(self) -> int:
        return len(self.real) + self.n_synthetic

    def source(self, key: int | EpochIndex) -> Pascal3DObject | SyntheticView:
        """The real object or synthetic view behind item ``key`` (an index in the current epoch or
        ``(epoch, index)``)."""
        epoch, i = self.epoch_and_index(key)
        if i < len(self.real):
            return self.real[i]
        g = np.random.default_rng(stable_seed("synthetic-draw", self.seed, epoch, i))
        return self.synthetic[int(g.integers(len(self.synthetic)))]

    def sample(self, key: int | EpochIndex) -> tuple[np.ndarray, np.ndarray, int]:
        """Item ``key`` before normalisation: ``(uint8 image (S, S, 3), rotation (3, 3) float64, class)``."""
        epoch, i = self.epoch_and_index(key)
        src = self.source(EpochIndex(epoch, i))
        image = decode_image(src.path if isinstance(src, SyntheticView) else src.image)
        width, height = image.size
        if isinstance(src, SyntheticView):
            box = np.array([0.0, 0.0, width, height])
            f = self.synthetic_focal
            K = np.array([[f, 0.0, width / 2], [0.0, f, height / 2], [0.0, 0.0, 1.0]])
        else:
            box = np.asarray(src.box, dtype=np.float64) - 0.5
            K = src.intrinsics()
        R = src.rotation
        roll = 0.0
        if self.augment is not None:
            g = np.random.default_rng(stable_seed("augment", self.seed, epoch, i))
            if self.augment["flip"] and g.random() < 0.5:
                image = ImageOps.mirror(image)
                box = hflip_box(box, width)
                K = K.copy()
                K[0, 2] = width - K[0, 2]
                R = hflip_rotation(R)
            j = self.augment["box_jitter"]
            if j > 0:
                w, h = box[2] - box[0], box[3] - box[1]
                jittered = box + g.uniform(-j, j, 4) * np.array([w, h, w, h])
                if jittered[2] > jittered[0] and jittered[3] > jittered[1]:
                    box = jittered
            roll = math.radians(self.augment["roll_std_deg"]) * g.standard_normal()
        H, W = box_to_virtual_camera(box, K, self.image_size, roll)
        pixels = warp_image(image, H, self.image_size)
        R = GL_TO_CV @ W @ GL_TO_CV @ R
        return pixels, R, src.class_index

    def __getitem__(self, key: int | EpochIndex) -> dict[str, torch.Tensor] | None:
        epoch, i = self.epoch_and_index(key)
        try:
            pixels, R, c = self.sample(EpochIndex(epoch, i))
        except CorruptImageError as e:
            skip_corrupt(e, self.on_corrupt, self._warned)
            return None
        return single_label_item(torch.from_numpy(pixels), c, i, R, self.return_all)


def check_augment(augment: dict | None) -> dict | None:
    if augment is None or augment is False:
        return None
    augment = {**DEFAULT_AUGMENT, **dict(augment)}
    unknown = set(augment) - set(DEFAULT_AUGMENT)
    if unknown:
        raise ConfigError(f"dataset.augment has unknown keys {sorted(unknown)} (known: {sorted(DEFAULT_AUGMENT)})")
    if not 0 <= float(augment["box_jitter"]) < 0.5:
        raise ConfigError(f"dataset.augment.box_jitter must be in [0, 0.5), got {augment['box_jitter']!r}")
    if float(augment["roll_std_deg"]) < 0:
        raise ConfigError(f"dataset.augment.roll_std_deg must be >= 0, got {augment['roll_std_deg']!r}")
    return {"flip": bool(augment["flip"]), "box_jitter": float(augment["box_jitter"]),
            "roll_std_deg": float(augment["roll_std_deg"])}  # fmt: skip
