"""What every pose network is: images in, a batch of distributions over SO(3) out.

A pose network (:class:`PoseNetwork`) maps images ``[B, 3, H, W]`` (and, with ``num_classes > 0``,
class indices ``[B]``) to its own output tensor, and says what that output means:

* :meth:`PoseNetwork.output_distribution` turns it into a
  :class:`~image2sphere.distributions.base.PoseDistribution` (a density family, the Fourier signal of
  I2S, or a point estimate), which training, evaluation, prediction and the plots use without
  knowing the method;
* :meth:`PoseNetwork.loss` is the method's own training loss, per image.

Adding a method is one subclass (with these two methods and ``forward``) plus one
``conf/model/<name>.yaml`` file (docs/configuration.md).
"""

from __future__ import annotations

from collections.abc import Callable

import torch
from torch import nn

from image2sphere.distributions.base import PoseDistribution

__all__ = ["PoseNetwork", "method_of"]


class PoseNetwork(nn.Module):
    """Shared parts: the encoder and the optional one-hot class channels; the method's interface.

    Args:
        encoder: an image encoder with ``out_channels`` and ``feature_size(image_size)``
            (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the size of the images the network is built for.
        num_classes: > 0: the class one-hot is appended to the feature map as constant channels.
    """

    def __init__(self, encoder: nn.Module, image_size: int | tuple[int, int], num_classes: int = 0):
        super().__init__()
        if isinstance(num_classes, bool) or not isinstance(num_classes, int) or num_classes < 0:
            raise ValueError(f"num_classes must be an integer >= 0, got {num_classes!r}")
        self.encoder = encoder
        self.num_classes = num_classes
        self.image_size = image_size
        self.feature_size = encoder.feature_size(image_size)
        self.feature_channels = encoder.out_channels + num_classes

    def features(self, images: torch.Tensor, class_index: torch.Tensor | None) -> torch.Tensor:
        """Encoder map ``[B, C (+ num_classes), h, w]``, with the class one-hot as constant channels."""
        x = self.encoder(images)
        if self.num_classes == 0:
            return x
        onehot = self.class_onehot(class_index, len(x)).to(x.dtype)  # [B, nc]
        return torch.cat([x, onehot[:, :, None, None].expand(-1, -1, *x.shape[-2:])], dim=1)

    def class_onehot(self, class_index: torch.Tensor | None, batch: int) -> torch.Tensor:
        """``class_index`` ``(B,)`` checked and one-hot encoded: ``(B, num_classes)``."""
        if class_index is None:
            raise ValueError(f"this model was built with num_classes={self.num_classes}: pass class_index")
        class_index = torch.as_tensor(class_index, device=next(self.parameters()).device)
        if class_index.shape != (batch,) or ((class_index < 0) | (class_index >= self.num_classes)).any():
            raise ValueError(
                f"class_index must be integers in [0, {self.num_classes}) of shape ({batch},), "
                f"got shape {tuple(class_index.shape)}"
            )
        return nn.functional.one_hot(class_index.long(), self.num_classes)

    def pooled_features(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """The feature map averaged over space: ``[B, C (+ num_classes)]`` (the baselines' input)."""
        return self.features(images, class_index).mean(dim=(-1, -2))

    # ------------------------------------------------------------------ the method's interface
    def output_distribution(self, output: torch.Tensor) -> PoseDistribution:
        """The batch of distributions that ``output = self(images)`` stands for."""
        raise NotImplementedError

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """The method's training loss per image ``(B,)`` for labels ``rotation (B, 3, 3)``; ``grid_level``
        is the training grid (used by the methods trained on a grid)."""
        raise NotImplementedError

    def distribution(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> PoseDistribution:
        """The predicted distribution over rotations for each image."""
        return self.output_distribution(self(images, class_index))


def method_of(net: nn.Module) -> tuple[Callable[[torch.Tensor], PoseDistribution], Callable[..., torch.Tensor]]:
    """``(output_distribution, loss)`` of a pose network. A bare module of SO(3) Fourier coefficients
    that only exposes its band limit ``.lmax`` (the interface before :class:`PoseNetwork`) means what
    I2S's output means: the Fourier signal of the log density, trained by the grid cross-entropy.
    ``ValueError`` for anything else."""
    if all(callable(getattr(net, m, None)) for m in ("output_distribution", "loss")):
        return net.output_distribution, net.loss
    lmax = getattr(net, "lmax", None)
    if isinstance(lmax, int) and not isinstance(lmax, bool):
        from image2sphere.so3.distribution import SO3Distribution, fourier_grid_nll

        return (
            lambda output: SO3Distribution(output, lmax),
            lambda output, rotation, grid_level: fourier_grid_nll(output, lmax, rotation, grid_level),
        )
    raise ValueError(
        f"model.net must be a pose network with output_distribution() and loss() "
        f"(image2sphere.nn.base.PoseNetwork), or a network of SO(3) Fourier coefficients that "
        f"exposes its band limit as .lmax; {type(net).__name__} is neither"
    )
