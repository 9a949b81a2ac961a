"""Distributions given by a normalizing flow on SO(3): an exact density, exact samples.

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; densities w.r.t. the Haar measure of
  volume ``pi^2`` (uniform: ``-log(pi^2)``).
* The flow is held as two callables of the per-image condition ``z (B, F)``:
  ``log_prob(z, rotations (K, 3, 3) or (B, K, 3, 3)) -> (B, K)``, the normalised log density by the
  change of variables, and ``sample(z, n, generator) -> (B, n, 3, 3)``, exact draws
  (:class:`image2sphere.nn.so3_flow.SO3Flow`). The normaliser is exactly 1 (``exact_log_normalizer``
  is 0), so the family reports its continuous log likelihood beside the grid protocol's, and
  :meth:`FlowDistribution.exact_sample` draws off the grid.
* Grid sweeps evaluate the flow in sub-chunks, as the implicit family does
  (:class:`~image2sphere.distributions.implicit.ImplicitDistribution`).
"""

from __future__ import annotations

from collections.abc import Callable

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.implicit import ImplicitDistribution

__all__ = ["FlowDistribution"]

SampleFn = Callable[[torch.Tensor, int, "torch.Generator | None"], torch.Tensor]


class FlowDistribution(ImplicitDistribution):
    """A batch of ``B`` flow densities ``p(R | z_b)``, normalised by construction.

    Args:
        condition: per-image conditions ``(B, F)`` (the network's output for the batch).
        log_prob: ``log_prob(condition, rotations) -> (B, K)``, the normalised log density.
        sample: ``sample(condition, n, generator) -> (B, n, 3, 3)``, exact draws.
        width: the widest hidden layer of the flow (sets the rotations per call).
    """

    def __init__(self, condition: torch.Tensor, log_prob, sample: SampleFn, width: int = 64):
        super().__init__(condition, log_prob, width)
        if not callable(sample):
            raise ConfigError(f"sample must be callable, got {type(sample).__name__}")
        self.sampler = sample

    def exact_log_normalizer(self) -> torch.Tensor:
        """``(B,)`` zeros: the change of variables gives a density that integrates to 1."""
        return self.features.new_zeros(self.batch_size)

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)``: uniform rotations pushed through the flow."""
        check_int("n", n, 1)
        with torch.no_grad():
            return self.sampler(self.features.detach(), n, generator)
