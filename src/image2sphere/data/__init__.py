"""Datasets: the SYMSOL renderer, dataset readers and LightningDataModules.

One module per job. Every reader shares :mod:`~image2sphere.data.common` (dataset errors, image
decoding, normalisation, the data seed) and :mod:`~image2sphere.data.safe_io` (pickles, npz and LMDB
read safely); loaders are built by :mod:`~image2sphere.data.datamodule` from the samplers and
collation of :mod:`~image2sphere.data.loading` and the worker policy of :mod:`~image2sphere.data.workers`.

Each published layout (described in docs/datasets.md) has a label reader and a Dataset module:
:mod:`~image2sphere.data.symsol_labels` and :mod:`~image2sphere.data.symsol` (SYMSOL I/II),
:mod:`~image2sphere.data.modelnet_labels` and :mod:`~image2sphere.data.modelnet` (ModelNet10-SO(3),
LMDB read directly), :mod:`~image2sphere.data.pascal3d_annotations` and
:mod:`~image2sphere.data.pascal3d` (PASCAL3D+ with RenderForCNN); their LightningDataModules are in
:mod:`~image2sphere.data.datamodule`, the one module here that imports Lightning. ``python -m image2sphere.data.verify``
(:mod:`~image2sphere.data.verify`, every dataset's checks) checks a download;
:mod:`image2sphere.data.fixtures` writes tiny copies.

The SYMSOL shapes are :mod:`~image2sphere.data.shapes` (geometry, marks) and
:mod:`~image2sphere.data.symmetry` (symmetry groups, equivalent rotations).

The ray caster is :mod:`image2sphere.data.raycast` (``render``); the writer of the SYMSOL layout is
:mod:`image2sphere.data.render` (``render_symsol``, and the command ``python -m image2sphere.data.render``),
imported on first use so that running it as a module does not find it already imported.
"""

from image2sphere.data.common import CorruptImageError, DatasetNotFoundError, load_image, normalize_images
from image2sphere.data.loading import EpochShuffleSampler
from image2sphere.data.modelnet import ModelNet10Dataset
from image2sphere.data.pascal3d import Pascal3DDataset
from image2sphere.data.shapes import SHAPES, SYMSOL_I_SHAPES, SYMSOL_II_SHAPES
from image2sphere.data.symmetry import equivalent_rotation_sets, equivalent_rotations, mark_visible, symmetry_group
from image2sphere.data.symsol import SymsolDataset
from image2sphere.data.symsol_labels import load_symsol_rotations

__all__ = [
    "SHAPES",
    "CorruptImageError",
    "DatasetNotFoundError",
    "FolderDataModule",
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


# imported on first use: render_symsol (so that ``python -m image2sphere.data.render`` does not find its module
# already imported) and the LightningDataModules, so that importing this package, as every loader worker does
# to unpickle its Dataset, does not import Lightning
_LAZY = {
    "render_symsol": "image2sphere.data.render",
    "FolderDataModule": "image2sphere.data.datamodule",
    "ModelNet10DataModule": "image2sphere.data.datamodule",
    "Pascal3DDataModule": "image2sphere.data.datamodule",
    "SymsolDataModule": "image2sphere.data.datamodule",
}


def __getattr__(name: str):
    if name in _LAZY:
        from importlib import import_module

        return getattr(import_module(_LAZY[name]), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
