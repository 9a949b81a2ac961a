"""ResNet image encoders from torchvision, without the pooling and classification layers."""

from __future__ import annotations

import math
import os

import torch
from torch import nn

from image2sphere.checks import ConfigError

__all__ = ["RESNET_DEPTHS", "ResNetEncoder"]

RESNET_DEPTHS = (18, 34, 50, 101, 152)


def _load_state_dict(path: str) -> dict[str, torch.Tensor]:
    try:
        state = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as err:  # unreadable or not a torch file
        raise ConfigError(f"encoder weights file {path!r} could not be read as a PyTorch state dict: {err}") from err
    if isinstance(state, dict) and "state_dict" in state and isinstance(state["state_dict"], dict):
        state = state["state_dict"]
    if not isinstance(state, dict):
        raise ConfigError(f"encoder weights file {path!r} holds a {type(state).__name__}, not a state dict")
    return state


class ResNetEncoder(nn.Module):
    """A torchvision ResNet up to its last residual stage: images ``[B, 3, H, W]`` -> ``[B, C, H/32, W/32]``.

    Args:
        depth: 18, 34, 50, 101 or 152.
        weights: ``None`` (random initialisation), a torchvision weights name (``"DEFAULT"``,
            ``"IMAGENET1K_V2"`` or ``"ResNet50_Weights.IMAGENET1K_V2"``; downloaded by torchvision
            into its cache when not there yet), or the path of a local state-dict file of the full
            torchvision ResNet (its ``fc.*`` entries are ignored).
    """

    def __init__(self, depth: int = 50, weights: str | None = None):
        super().__init__()
        from torchvision import models  # after the torchvision guard in image2sphere/__init__.py

        if depth not in RESNET_DEPTHS:
            raise ConfigError(f"encoder depth must be one of {RESNET_DEPTHS}, got {depth!r}")
        self.depth = depth
        net = getattr(models, f"resnet{depth}")(weights=None)
        if weights is not None:
            self._load(net, str(weights), models)
        self.body = nn.Sequential(*list(net.children())[:-2])  # drop avgpool and fc
        self.out_channels = 512 if depth < 50 else 2048

    def _load(self, net: nn.Module, weights: str, models) -> None:
        if os.path.sep in weights or weights.endswith((".pt", ".pth", ".ckpt", ".bin")) or os.path.exists(weights):
            if not os.path.isfile(weights):
                raise ConfigError(f"encoder weights file {weights!r} does not exist")
            state = {k: v for k, v in _load_state_dict(weights).items() if not k.startswith("fc.")}
            try:
                missing, unexpected = net.load_state_dict(state, strict=False)
                problem = ""
            except RuntimeError as err:  # shape mismatches
                missing, unexpected, problem = [], [], str(err).splitlines()[1:3]
            missing = [k for k in missing if not k.startswith("fc.")]
            if missing or unexpected or problem:
                raise ConfigError(
                    f"encoder weights file {weights!r} does not fit resnet{self.depth}: "
                    f"missing {missing[:5]}, unexpected {unexpected[:5]} {problem}"
                )
            return
        name = weights if "." in weights else f"ResNet{self.depth}_Weights.{weights}"
        try:
            enum = models.get_weight(name)
        except (ValueError, KeyError, AttributeError) as err:
            raise ConfigError(
                f"unknown torchvision weights {weights!r} for resnet{self.depth}; use null, a name such as "
                f"IMAGENET1K_V1, or a local file path"
            ) from err
        try:
            net.load_state_dict(enum.get_state_dict(progress=False))
        except Exception as err:  # download failed (no network) or corrupt cache
            raise RuntimeError(
                f"could not load torchvision weights {name} ({err}). Without network access, download the file "
                f"elsewhere and pass its path as the encoder weights, or use weights=null (random init)."
            ) from err

    def feature_size(self, image_size: int | tuple[int, int]) -> tuple[int, int]:
        """Spatial size of the output map for an input of ``image_size`` (224 -> 7 x 7)."""
        h, w = (image_size, image_size) if isinstance(image_size, int) else image_size
        for _ in range(5):  # stem conv, max pool, and the three strided stages each halve (rounding up)
            h, w = math.ceil(h / 2), math.ceil(w / 2)
        return h, w

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ConfigError(f"images must have shape (batch, 3, H, W), got {tuple(images.shape)}")
        return self.body(images)
