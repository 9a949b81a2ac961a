"""The rotation labels that losses, distributions and metrics take, checked in one place.

Conventions
-----------
* One label per image: ``rotation (B, 3, 3)`` (:func:`check_labels`), what every training loss takes.
* A set of equivalent rotations per image (a symmetric object's labels): ``targets (B, M, 3, 3)`` with
  ``mask (B, M)``, ``True`` where an entry is real; sets of fewer than ``M`` rotations are padded. The
  first entry of every image is real (its rendering rotation, :func:`check_target_mask`); padding may sit
  anywhere after it and may hold anything, NaN included, until :func:`fill_padding` replaces it by the
  image's first rotation.
* :func:`check_targets` checks a set as the metrics and the evaluation read it (a missing mask: every
  entry real), :func:`check_rotation_set` as the set losses read it (beside the network's output).

This module imports torch only, so that every layer of the package (distributions, networks, metrics,
training) can use it.
"""

from __future__ import annotations

import torch

from image2sphere.checks import ConfigError

__all__ = ["check_labels", "check_rotation_set", "check_target_mask", "check_targets", "fill_padding"]


def check_labels(rotation: object, batch: int, name: str = "rotation") -> torch.Tensor:
    """``rotation`` if it is a tensor of shape ``(batch, 3, 3)`` (one label per image), else ``ValueError``
    naming ``name``, the shape expected and the one given."""
    if not isinstance(rotation, torch.Tensor) or rotation.shape != (batch, 3, 3):
        shape = tuple(rotation.shape) if isinstance(rotation, torch.Tensor) else type(rotation).__name__
        raise ConfigError(f"{name} must have shape ({batch}, 3, 3), got {shape}")
    return rotation


def check_targets(targets: torch.Tensor, mask: torch.Tensor | None, batch: int | None = None) -> torch.Tensor:
    """Validate ``targets (B, M, 3, 3)`` and return the mask ``(B, M)`` (all real when ``None``; else bool and
    passing :func:`check_target_mask`)."""
    if targets.ndim != 4 or targets.shape[-2:] != (3, 3) or targets.shape[1] < 1:
        raise ConfigError(f"targets must have shape (B, M, 3, 3) with M >= 1, got {tuple(targets.shape)}")
    if batch is not None and targets.shape[0] != batch:
        raise ConfigError(f"targets must have batch size {batch}, got {tuple(targets.shape)}")
    if mask is None:
        return torch.ones(targets.shape[:2], dtype=torch.bool, device=targets.device)
    if mask.shape != targets.shape[:2] or mask.dtype != torch.bool:
        raise ConfigError(
            f"mask must be bool of shape {tuple(targets.shape[:2])}, got {tuple(mask.shape)} {mask.dtype}"
        )
    return check_target_mask(mask)


def check_target_mask(mask: torch.Tensor) -> torch.Tensor:
    """``mask (B, M)`` of a padded target set if every image's first target is real, else ``ValueError``.

    The one rule on where padding may sit, for :func:`check_targets` (metrics, evaluation) and
    :func:`check_rotation_set` (the set losses): ``targets[:, 0]`` must be real, the other entries may be
    real or padding in any order. Every loader builds such masks: the first entry is the rendering rotation
    (``arange(M) < count`` with ``count >= 1`` for SYMSOL, all True for one-label sets). A first entry that
    is padding is refused rather than repaired (say by filling padding from each image's first real entry)
    because ``targets[:, 0]`` is read on its own elsewhere too (the validation step's one-label loss,
    :mod:`image2sphere.training.module`), not only by :func:`fill_padding`, which copies it into the
    padding: a padded first entry (possibly NaN) would be read as a rotation, giving a NaN loss or metric or
    an error far from its cause.
    """
    if not mask.any(1).all():
        raise ConfigError("every image needs at least one real rotation in mask")
    if not mask[:, :1].all():
        raise ConfigError(
            "mask[:, 0] must be True: the first target of every image is its rendering rotation, "
            "and padding is read as it; put a real rotation first in every image's set"
        )
    return mask


def check_rotation_set(output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor) -> None:
    """``ValueError`` unless ``rotations (B, M, 3, 3)`` and ``mask (B, M)`` match the ``B`` rows of ``output``
    and every image's first rotation is real (:func:`check_target_mask`, the rule of the metrics too): the
    arguments of :meth:`image2sphere.nn.base.PoseNetwork.set_loss`."""
    if mask.ndim != 2 or rotations.shape != (*mask.shape, 3, 3) or len(output) != len(mask):
        raise ConfigError(
            f"rotations (B, M, 3, 3) and mask (B, M) must match the output's batch of {len(output)}, "
            f"got {tuple(rotations.shape)} and {tuple(mask.shape)}"
        )
    check_target_mask(mask)


def fill_padding(targets: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """``targets (B, M, 3, 3)`` with the padding entries (possibly NaN) replaced by the image's first target,
    so they can be read safely; ``mask (B, M)`` must pass :func:`check_target_mask` (the first target real)."""
    return torch.where(mask[..., None, None], targets, targets[:, :1].expand_as(targets))  # [B, M, 3, 3]
