"""The catalogue of finite rotation groups, built from scipy.

Conventions
-----------
* A group is a float64 tensor ``(G, 3, 3)`` of rotation matrices (column vectors, as in
  :mod:`image2sphere.so3.rotations`) whose element 0 is exactly the identity.
* The elements are ``scipy.spatial.transform.Rotation.create_group(name).as_matrix()``: ``"T"``
  (tetrahedral, 12), ``"O"`` (octahedral, 24), ``"I"`` (icosahedral, 60), ``"C<n>"`` (cyclic about
  ``z``, n) and ``"D<n>"`` (dihedral, 2n). Where every entry is within ``1e-9`` of an integer (T, O
  and some C, D), the entries are snapped to exact ``0`` and ``+-1``.
* Order: scipy's, with the identity moved to the front (``sort=False``), or sorted
  lexicographically by the nine entries rounded to 9 decimals, then the identity moved to the front
  (``sort=True``). Both orders are fixed: SYMSOL's equivalent rotations use the first, the anchors of
  the icosahedral network (whose checkpoints store weights per anchor) the second.
"""

from __future__ import annotations

import functools
import re

import numpy as np
import torch

from image2sphere.checks import ConfigError

__all__ = ["rotation_group"]

_NAME = re.compile(r"^(?:[TOI]|[CD][1-9]\d*)$")


@functools.cache
def _rotation_group_np(name: str, sort: bool) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    G = Rotation.create_group(name).as_matrix()  # [G, 3, 3]
    snapped = np.round(G)
    if np.abs(G - snapped).max() < 1e-9:  # entries exactly 0 and +-1
        G = snapped + 0.0
    if sort:
        G = G[np.lexsort(np.round(G.reshape(len(G), 9), 9).T[::-1])]  # by the first entry, then the next...
    dist = np.abs(G - np.eye(3)).reshape(len(G), 9).max(axis=1)
    i = int(np.argmin(dist))
    if dist[i] > 1e-9:
        raise RuntimeError(f"scipy's group {name!r} has no identity element")
    G = np.concatenate([np.eye(3)[None], np.delete(G, i, axis=0)])  # the identity first, exactly
    G.flags.writeable = False
    return G


def rotation_group(name: str, *, sort: bool = False) -> torch.Tensor:
    """The finite rotation group ``name`` (``"T"``, ``"O"``, ``"I"``, ``"C<n>"``, ``"D<n>"``) as a
    float64 tensor ``(G, 3, 3)``, identity first, in scipy's order or (``sort=True``) the
    lexicographic one (module docstring). A fresh tensor on each call."""
    if not isinstance(name, str) or not _NAME.match(name):
        raise ConfigError(f"name must be 'T', 'O', 'I', 'C<n>' or 'D<n>' (n >= 1), got {name!r}")
    return torch.from_numpy(_rotation_group_np(name, bool(sort)).copy())
