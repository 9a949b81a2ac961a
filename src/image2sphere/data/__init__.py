"""Datasets: the SYMSOL renderer, dataset readers and LightningDataModules.

Readers of the published layouts (described in docs/datasets.md): :mod:`~image2sphere.data.symsol` (SYMSOL I/II),
:mod:`~image2sphere.data.modelnet` (ModelNet10-SO(3), LMDB read directly),
:mod:`~image2sphere.data.pascal3d` (PASCAL3D+ with RenderForCNN). ``python -m
image2sphere.data.verify`` checks a download; :mod:`image2sphere.data.fixtures` writes tiny copies.

The ray caster is :mod:`image2sphere.data.raycast` (``render``); the writer of the SYMSOL layout is
:mod:`image2sphere.data.render` (``render_symsol``, and the command ``python -m image2sphere.data.render``),
imported on first use so that running it as a module does not find it already imported.
"""

from image2sphere.data.common import CorruptImageError, DatasetNotFoundError, load_image, normalize_images
from image2sphere.data.loading import EpochShuffleSampler
from image2sphere.data.modelnet import ModelNet10DataModule, ModelNet10Dataset
from image2sphere.data.pascal3d import Pascal3DDataModule, Pascal3DDataset
from image2sphere.data.shapes import SHAPES, SYMSOL_I_SHAPES, SYMSOL_II_SHAPES
from image2sphere.data.symmetry import equivalent_rotation_sets, equivalent_rotations, mark_visible, symmetry_group
from image2sphere.data.symsol import SymsolDataModule, SymsolDataset
from image2sphere.data.symsol_labels import load_symsol_rotations

__all__ = [
    "SHAPES",
    "CorruptImageError",
    "DatasetNotFoundError",
    "ModelNet10DataModule",
    "ModelNet10Dataset",
    "Pascal3DDataModule",
    "Pascal3DDataset",
    "SYMSOL_II_SHAPES",
    "SYMSOL_I_SHAPES",
    "EpochShuffleSampler",
    "SymsolDataModule",
    "SymsolDataset",
    "equivalent_rotation_sets",
    "equivalent_rotations",
    "load_image",
    "load_symsol_rotations",
    "mark_visible",
    "normalize_images",
    "render_symsol",
    "symmetry_group",
]


def __getattr__(name: str):
    if name == "render_symsol":
        from image2sphere.data.render import render_symsol

        return render_symsol
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
