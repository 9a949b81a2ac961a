"""Implicit distributions over SO(3): an unnormalised log density given by a network (Implicit-PDF).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; densities w.r.t. the Haar measure of
  volume ``pi^2`` (uniform: ``-log(pi^2)``).
* The family is ``log p(R | x) = f(x, R) - log Z(x)`` with ``f`` a network's scalar output
  (Murphy et al. 2021, "Implicit-PDF"). ``Z`` has no closed form: the density is the grid
  protocol's (:class:`~image2sphere.distributions.base.PoseDistribution`), the softmax of ``f``
  over the HEALPix grid of a level, ``p_nearest * N / pi^2``.
* The network is held as a callable ``score(features (B, F), rotations (K, 3, 3) or (B, K, 3, 3))
  -> (B, K)`` and evaluated lazily, in sub-chunks of at most :data:`MAX_ACTIVATION_ELEMENTS`
  hidden values (``B x k x width``; on a CPU :data:`CPU_ACTIVATION_ELEMENTS`, cache-sized), so a grid
  chunk of the base class (``CHUNK_POINTS`` rotations) never builds a ``(B, CHUNK_POINTS, width)``
  activation.
* Evaluated without gradients, the values at a query tensor are kept (up to :data:`MAX_MEMO_ELEMENTS`
  per distribution, with the query tensor, so its memory is not reused meanwhile): the grid sweeps of one
  test batch (the log normaliser and highest-density masses, the recalibrated distribution's, which
  divides the same values by its temperature, and the spread) then run the network over the grid once.
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import PoseDistribution

__all__ = ["CPU_ACTIVATION_ELEMENTS", "MAX_ACTIVATION_ELEMENTS", "MAX_MEMO_ELEMENTS", "ImplicitDistribution"]

# hidden values (B x k x width) per call of the scoring network: 64 MiB of float32 per activation at most
MAX_ACTIVATION_ELEMENTS = 1 << 24
# on a CPU, 4 MiB, so that each layer's output is still in cache when the next reads it. A level-3 sweep of
# 16 images on this project's 2-core CPU: IPDF 0.91 s at 1 << 20 against 2.14 s at 1 << 24 (1.02 s at
# 1 << 19), the flow 2.1 s against 3.7 s (2.7 s at 1 << 18); benchmarks/flow_grid.py. A GPU keeps the
# larger calls: each call is a launch of every layer's kernels.
CPU_ACTIVATION_ELEMENTS = 1 << 20
# log densities kept per distribution for repeated queries without gradients (256 MiB of float32)
MAX_MEMO_ELEMENTS = 1 << 26


def _version(tensor: torch.Tensor) -> int:
    """The in-place write counter of ``tensor``; -1 for an inference tensor, which has none (Lightning's test
    loop: its queries are the grid's and the labels, never written in place)."""
    return -1 if tensor.is_inference() else tensor._version


def _memo_key(rotations: torch.Tensor) -> tuple:
    """The memory a query tensor views (storage, offset, shape, strides) and its version (in-place writes)."""
    return (rotations.untyped_storage().data_ptr(), rotations.storage_offset(), tuple(rotations.shape),
            rotations.stride(), _version(rotations), rotations.dtype, rotations.device)  # fmt: skip


ScoreFn = Callable[[torch.Tensor, torch.Tensor], torch.Tensor]


class ImplicitDistribution(PoseDistribution):
    """A batch of ``B`` distributions ``p(R) ~ exp(score(features_b, R))``.

    Args:
        features: per-image features ``(B, F)`` (the network's output for the batch).
        score: ``score(features (B, F), rotations (k, 3, 3) or (B, k, 3, 3)) -> (B, k)``, the
            unnormalised log density (e.g. :meth:`image2sphere.nn.IPDF.score`). Differentiable
            w.r.t. the features and the network's parameters.
        width: the widest hidden layer of ``score``: sets the rotations per call,
            ``max(1, budget // (B * width))``, the budget :data:`MAX_ACTIVATION_ELEMENTS` (on a CPU at
            most :data:`CPU_ACTIVATION_ELEMENTS`).
    """

    def __init__(self, features: torch.Tensor, score: ScoreFn, width: int = 256):
        if not isinstance(features, torch.Tensor) or features.ndim != 2 or features.shape[0] == 0:
            shape = tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__
            raise ConfigError(f"features must have shape (B, F) with B >= 1, got {shape}")
        if not callable(score):
            raise ConfigError(f"score must be callable, got {type(score).__name__}")
        check_int("width", width, 1)
        self.features = features
        self.score = score
        self.width = width
        self.batch_size, self.dtype, self.device = features.shape[0], features.dtype, features.device
        budget = MAX_ACTIVATION_ELEMENTS
        if self.device.type == "cpu":
            budget = min(budget, CPU_ACTIVATION_ELEMENTS)
        self.points_per_call = max(1, budget // (self.batch_size * width))
        self._memo: dict[tuple, tuple[torch.Tensor, torch.Tensor]] = {}
        self._memo_elements = 0

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """``score`` at ``(K, 3, 3)`` (shared) or ``(B, K, 3, 3)`` rotations: ``(B, K)``, evaluated
        :attr:`points_per_call` rotations at a time."""
        if not isinstance(rotations, torch.Tensor) or rotations.ndim not in (3, 4) or rotations.shape[-2:] != (3, 3):
            shape = tuple(rotations.shape) if isinstance(rotations, torch.Tensor) else type(rotations).__name__
            raise ConfigError(f"rotations must have shape (K, 3, 3) or (B, K, 3, 3), got {shape}")
        if rotations.ndim == 4 and rotations.shape[0] != self.batch_size:
            raise ConfigError(
                f"rotations of shape (B, K, 3, 3) must have B = batch size {self.batch_size}, "
                f"got {tuple(rotations.shape)}"
            )
        rotations = rotations.to(device=self.device, dtype=self.dtype)
        n = rotations.shape[-3]
        if n == 0:
            return self.features.new_zeros(self.batch_size, 0)
        key = None if torch.is_grad_enabled() else _memo_key(rotations)
        if key is not None and key in self._memo:
            return self._memo[key][1]
        step = self.points_per_call
        parts = [self.score(self.features, rotations[..., s : s + step, :, :]) for s in range(0, n, step)]
        values = parts[0] if len(parts) == 1 else torch.cat(parts, dim=1)  # [B, K]
        if key is not None and self._memo_elements + values.numel() <= MAX_MEMO_ELEMENTS:
            self._memo[key] = (rotations, values)  # the rotations held: their memory cannot be reused meanwhile
            self._memo_elements += values.numel()
        return values
