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

Conventions: mixed precision (:mod:`image2sphere.precision`)
-----------------------------------------------------------
* Under an enclosing ``torch.autocast`` (``trainer.precision=bf16-mixed`` or ``16-mixed``) only the
  encoder runs in reduced precision: :meth:`Float32Head.encode` (behind :meth:`PoseNetwork.features`
  and :meth:`PoseNetwork.pooled_features`) runs it under that autocast and returns float32 features.
* Everything else computes in float32 by construction: :class:`Float32Head` wraps ``forward``,
  ``output_distribution`` and ``loss`` of every subclass, when the subclass is defined, in
  :func:`~image2sphere.precision.float32_region` (autocast off, float16/bfloat16 tensor arguments cast
  to float32). A new method gets this without writing anything; its ``forward`` reads the images
  through ``features``, ``pooled_features`` or ``encode`` (a direct ``self.encoder(...)`` call would
  run the encoder in float32 too: correct, only slower).
* Without autocast nothing changes: the wrappers call the methods as they are.

Input scaling
-------------
The data pipeline hands every network ImageNet-normalised images, ``(pixels / 255 - mean) / std``
(:func:`image2sphere.data.common.normalize_images`), what torchvision's pretrained weights expect.
A network built with ``input_scaling="unit"`` maps them back to ``pixels / 255`` in ``[0, 1]`` (the
original I2S research code's input) before its encoder sees them: :meth:`Float32Head.encode` applies
:func:`unscale_imagenet` (the default ``"imagenet"`` passes the images on unchanged).
"""

from __future__ import annotations

import functools
from collections.abc import Callable

import torch
from torch import nn

from image2sphere.checks import ConfigError, check_int
from image2sphere.data.common import IMAGENET_MEAN, IMAGENET_STD
from image2sphere.distributions.base import PoseDistribution
from image2sphere.distributions.fourier import SO3Distribution, fourier_grid_nll
from image2sphere.precision import encoder_autocast, float32_methods, float32_region, to_float32
from image2sphere.rotation_sets import check_labels, check_rotation_set

__all__ = ["INPUT_SCALINGS", "Float32Head", "PoseNetwork", "check_input_scaling", "method_of", "unscale_imagenet"]

#: ``model.net.input_scaling``: what the encoder sees (module docstring, "Input scaling")
INPUT_SCALINGS = ("imagenet", "unit")


def check_input_scaling(value) -> str:
    """``value`` if it is one of :data:`INPUT_SCALINGS`, else ``ValueError`` naming the config key."""
    if not isinstance(value, str) or value not in INPUT_SCALINGS:
        raise ConfigError(
            f"model.net.input_scaling must be one of {INPUT_SCALINGS}, got {value!r}: 'imagenet' feeds the "
            "encoder the ImageNet-normalised images as the data pipeline gives them, 'unit' maps them back to "
            "pixels / 255 first (the original I2S code)"
        )
    return value


def unscale_imagenet(images: torch.Tensor) -> torch.Tensor:
    """ImageNet-normalised images ``[B, 3, H, W]`` -> ``pixels / 255`` in ``[0, 1]``: ``x * std + mean``,
    the inverse of :func:`image2sphere.data.common.normalize_images`'s normalisation."""
    if images.ndim != 4 or images.shape[1] != 3:
        raise ConfigError(f"images must have shape (batch, 3, H, W), got {tuple(images.shape)}")
    mean = torch.tensor(IMAGENET_MEAN, dtype=images.dtype, device=images.device)[:, None, None]
    std = torch.tensor(IMAGENET_STD, dtype=images.dtype, device=images.device)[:, None, None]
    return images * std + mean


class Float32Head(nn.Module):
    """A network with an image ``encoder`` whose every other part computes in float32 under autocast.

    Each subclass's own :attr:`FLOAT32_METHODS` are wrapped in
    :func:`~image2sphere.precision.float32_region` when the subclass is defined; :meth:`encode` runs
    ``self.encoder`` under the autocast that enclosed the call (module docstring).
    """

    #: methods that run with autocast off and float16/bfloat16 tensor arguments cast to float32
    FLOAT32_METHODS: tuple[str, ...] = ("forward", "output_distribution", "loss")

    encoder: nn.Module
    #: what the encoder sees, one of :data:`INPUT_SCALINGS` (module docstring); set by subclasses that
    #: take it as an argument (:class:`PoseNetwork`)
    input_scaling: str = "imagenet"

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        float32_methods(cls, cls.FLOAT32_METHODS)

    def encode(self, images: torch.Tensor) -> torch.Tensor:
        """``self.encoder(images)``, the one part that follows an enclosing autocast; its output as
        float32 when it ran under autocast (else unchanged). With ``input_scaling="unit"`` the encoder
        gets :func:`unscale_imagenet` of ``images`` ``[B, 3, H, W]`` (computed before the autocast)."""
        if self.input_scaling == "unit":
            images = unscale_imagenet(images)
        with encoder_autocast() as mixed:
            x = self.encoder(images)
        return to_float32(x) if mixed else x


class PoseNetwork(Float32Head):
    """Shared parts: the encoder and the optional one-hot class channels; the method's interface.

    Args:
        encoder: an image encoder with ``out_channels`` and ``feature_size(image_size)``
            (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the size of the images the network is built for.
        num_classes: > 0: the class one-hot is appended to the feature map as constant channels.
        input_scaling: ``"imagenet"`` (the images as the data pipeline normalises them) or ``"unit"``
            (mapped back to ``pixels / 255`` before the encoder); module docstring, "Input scaling".
    """

    FLOAT32_METHODS = (*Float32Head.FLOAT32_METHODS, "set_loss")

    def __init_subclass__(cls, **kwargs):
        """Every method's own :meth:`loss` refuses a label of another shape than ``(B, 3, 3)`` with one
        message (:func:`~image2sphere.rotation_sets.check_labels`) before it computes anything."""
        super().__init_subclass__(**kwargs)
        loss = vars(cls).get("loss")
        if loss is not None:
            cls.loss = _labels_checked(loss)

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int],
        num_classes: int = 0,
        input_scaling: str = "imagenet",
    ):
        super().__init__()
        check_int("num_classes", num_classes, 0)
        self.input_scaling = check_input_scaling(input_scaling)
        self.encoder = encoder
        self.num_classes = num_classes
        self.image_size = image_size
        self.feature_size = encoder.feature_size(image_size)
        self.feature_channels = encoder.out_channels + num_classes

    def features(self, images: torch.Tensor, class_index: torch.Tensor | None) -> torch.Tensor:
        """Encoder map ``[B, C (+ num_classes), h, w]``, with the class one-hot as constant channels
        (float32 under autocast, :meth:`encode`)."""
        x = self.encode(images)
        if self.num_classes == 0:
            return x
        onehot = self.class_onehot(class_index, len(x)).to(x.dtype)  # [B, nc]
        return torch.cat([x, onehot[:, :, None, None].expand(-1, -1, *x.shape[-2:])], dim=1)

    def class_onehot(self, class_index: torch.Tensor | None, batch: int) -> torch.Tensor:
        """``class_index`` ``(B,)`` checked and one-hot encoded: ``(B, num_classes)``."""
        if class_index is None:
            raise ConfigError(f"this model was built with num_classes={self.num_classes}: pass class_index")
        class_index = torch.as_tensor(class_index, device=next(self.parameters()).device)
        if class_index.shape != (batch,) or ((class_index < 0) | (class_index >= self.num_classes)).any():
            raise ConfigError(
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

    def set_loss(
        self, output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor, grid_level: int
    ) -> torch.Tensor:
        """The training loss per image ``(B,)`` averaged over each image's equivalent rotations
        ``rotations (B, M, 3, 3)`` where ``mask (B, M)`` (``dataset.label=all``): exactly the expectation
        of :meth:`loss` for one label drawn uniformly from the set, what ``dataset.label=random`` trains
        on average. A method may compute it faster (I2S: one normaliser per image)."""
        return mean_loss_over_set(self.loss, output, rotations, mask, grid_level)

    def distribution(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> PoseDistribution:
        """The predicted distribution over rotations for each image."""
        return self.output_distribution(self(images, class_index))


def _labels_checked(loss: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
    """``loss(self, output, rotation, ...)`` that first checks ``rotation`` against the ``B`` rows of
    ``output`` (:meth:`PoseNetwork.__init_subclass__`)."""

    @functools.wraps(loss)
    def checked(self, output: torch.Tensor, rotation: torch.Tensor, *args, **kwargs) -> torch.Tensor:
        check_labels(rotation, len(output))
        return loss(self, output, rotation, *args, **kwargs)

    return checked


def mean_loss_over_set(
    loss: Callable[..., torch.Tensor],
    output: torch.Tensor,
    rotations: torch.Tensor,
    mask: torch.Tensor,
    grid_level: int,
) -> torch.Tensor:
    """``(B,)``: the mean of ``loss(output, rotation, grid_level)`` over the rotations of each image
    (``rotations (B, M, 3, 3)``, real where ``mask (B, M)``, the first of each image among them), by evaluating
    ``loss`` once per real rotation on its image's output (the rows of ``output`` repeated), a batch of
    ``B`` rows at a time: as much memory as one ordinary step, and ``K / B`` times its loss's time for
    ``K`` real rotations (a cone's 360 or a cylinder's 720 per image make it that much slower)."""
    check_rotation_set(output, rotations, mask)
    counts = mask.sum(1)
    image, k = mask.nonzero(as_tuple=True)  # [K], [K]
    # in pieces of one batch each: the memory of one ordinary step, the time of K / B of them
    size = len(mask)
    per_rotation = torch.cat(
        [loss(output[i], rotations[i, j], grid_level) for i, j in zip(image.split(size), k.split(size), strict=True)]
    )  # [K]
    total = torch.zeros(len(mask), dtype=per_rotation.dtype, device=per_rotation.device)
    return total.index_add(0, image.to(per_rotation.device), per_rotation) / counts.to(per_rotation)


def set_loss_of(net: nn.Module, loss: Callable[..., torch.Tensor]) -> Callable[..., torch.Tensor]:
    """The loss averaged over equivalent rotations for ``net`` (its :meth:`PoseNetwork.set_loss`, or
    :func:`mean_loss_over_set` of ``loss`` for a bare network of Fourier coefficients)."""
    own = getattr(net, "set_loss", None)
    if callable(own):
        return own
    return lambda output, rotations, mask, grid_level: mean_loss_over_set(loss, output, rotations, mask, grid_level)


def method_of(net: nn.Module) -> tuple[Callable[[torch.Tensor], PoseDistribution], Callable[..., torch.Tensor]]:
    """``(output_distribution, loss)`` of a pose network. A bare module of SO(3) Fourier coefficients
    that only exposes its band limit ``.lmax`` (the interface before :class:`PoseNetwork`) means what
    I2S's output means: the Fourier signal of the log density, trained by the grid cross-entropy.
    ``ValueError`` for anything else."""
    if all(callable(getattr(net, m, None)) for m in ("output_distribution", "loss")):
        return net.output_distribution, net.loss
    lmax = getattr(net, "lmax", None)
    if isinstance(lmax, int) and not isinstance(lmax, bool):
        return (  # in float32 under autocast, as a pose network's own methods
            float32_region(lambda output: SO3Distribution(output, lmax)),
            float32_region(lambda output, rotation, grid_level: fourier_grid_nll(output, lmax, rotation, grid_level)),
        )
    raise ConfigError(
        f"model.net must be a pose network with output_distribution() and loss() "
        f"(image2sphere.nn.base.PoseNetwork), or a network of SO(3) Fourier coefficients that "
        f"exposes its band limit as .lmax; {type(net).__name__} is neither"
    )
