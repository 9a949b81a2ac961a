"""Training and evaluation with Lightning, configured by Hydra (see ``conf/`` and ``src/train.py``).

The names below are imported on first use (PEP 562): ``import image2sphere.training.resolvers`` and the
other light modules of this package do not import Lightning and the networks, so that an entry point's
``--help``, its command-line checks and the loader workers that run the entry module again (as
``__mp_main__``, under ``forkserver`` or ``spawn``) do not pay for them.
"""

from __future__ import annotations

from importlib import import_module
from typing import TYPE_CHECKING

__all__ = ["NonFiniteLossError", "PoseEstimationModule", "register_resolvers", "train"]

_HOMES = {
    "NonFiniteLossError": "image2sphere.training.module",
    "PoseEstimationModule": "image2sphere.training.module",
    "train": "image2sphere.training.pipeline",
    "register_resolvers": "image2sphere.training.resolvers",
}

if TYPE_CHECKING:
    from image2sphere.training.module import NonFiniteLossError, PoseEstimationModule
    from image2sphere.training.pipeline import train
    from image2sphere.training.resolvers import register_resolvers


def __getattr__(name: str):
    home = _HOMES.get(name)
    if home is None:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(import_module(home), name)
    globals()[name] = value  # imported once
    return value


def __dir__() -> list[str]:
    return sorted([*globals(), *__all__])
