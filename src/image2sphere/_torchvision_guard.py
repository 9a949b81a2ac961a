"""Make ``import torchvision`` work on a CPU-only PyTorch.

The torchvision 0.28.0 wheel on PyPI is built against CUDA. On the CPU build of torch 2.13.0
its compiled extension cannot be loaded, and ``torchvision/_meta_registrations.py`` then fails
at import with ``RuntimeError: operator torchvision::nms does not exist``. Lightning imports
torchvision through torchmetrics, so ``import lightning`` fails as well.

:func:`install` must run before torchvision is first imported. It first tries to load
torchvision's own extension exactly as torchvision would; where that works (a matching CPU or CUDA
build) it does nothing else. Where it fails, it declares the two operator schemas that the Python
side of torchvision registers fake kernels for (``nms`` and ``qnms``), without any kernel. The pure
Python parts (``torchvision.models``, ``transforms.v2``) then work; ``torchvision.ops.nms`` and
``torchvision.io`` decoding stay unavailable, which is why this project reads images with Pillow.
"""

from __future__ import annotations

import glob
import importlib.util
import os
import sys

import torch

_SCHEMAS = {
    "nms": "nms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
    "qnms": "qnms(Tensor dets, Tensor scores, float iou_threshold) -> Tensor",
}
_library: torch.library.Library | None = None  # kept alive: dropping it unregisters the schemas


def _operator_exists(name: str) -> bool:
    try:
        getattr(torch.ops.torchvision, name)
    except (AttributeError, RuntimeError):
        return False
    return True


def _extension_loads() -> bool:
    """Whether torchvision's compiled ``_C`` extension loads on this torch (loading it if so)."""
    spec = importlib.util.find_spec("torchvision")
    if spec is None or not spec.submodule_search_locations:
        return False
    for folder in spec.submodule_search_locations:
        for path in glob.glob(os.path.join(folder, "_C*")):
            try:
                torch.ops.load_library(path)
                return True
            except (OSError, RuntimeError):
                return False
    return False


def install() -> bool:
    """Declare the missing torchvision operator schemas if needed.

    Returns True when the schemas were declared here, False when nothing had to be done
    (torchvision already imported, its extension loads, or torchvision is not installed).
    """
    global _library
    if _library is not None or "torchvision" in sys.modules:
        return False
    if all(_operator_exists(name) for name in _SCHEMAS) or _extension_loads():
        return False
    if importlib.util.find_spec("torchvision") is None:
        return False
    _library = torch.library.Library("torchvision", "DEF")
    for name, schema in _SCHEMAS.items():
        if not _operator_exists(name):
            _library.define(schema)
    return True
