"""Image encoders from torchvision, without their pooling and classification layers: the ResNets of the paper
(:class:`ResNetEncoder`) and any torchvision classification model whose family has a spatial feature map
(:class:`TorchvisionEncoder`: ConvNeXt, EfficientNet, RegNet, MobileNet, VGG, DenseNet, Swin, ViT ...)."""

from __future__ import annotations

import math
import os

import torch
from torch import nn

from image2sphere.checks import ConfigError

__all__ = ["RESNET_DEPTHS", "ResNetEncoder", "TorchvisionEncoder"]

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


def load_weights(net: nn.Module, weights: str, model: str, enum: str | None, head: tuple[str, ...]) -> None:
    """Load ``weights`` into the torchvision model ``net`` (named ``model``): a local state-dict file (its
    entries starting with ``head``, the classifier, ignored) or a torchvision weights name (``"DEFAULT"``,
    ``"IMAGENET1K_V1"`` of the weights enum ``enum``, or a full ``"<Enum>.<NAME>"``)."""
    from torchvision import models

    if os.path.sep in weights or weights.endswith((".pt", ".pth", ".ckpt", ".bin")) or os.path.exists(weights):
        if not os.path.isfile(weights):
            raise ConfigError(f"encoder weights file {weights!r} does not exist")
        state = {k: v for k, v in _load_state_dict(weights).items() if not k.startswith(head)}
        try:
            missing, unexpected = net.load_state_dict(state, strict=False)
            problem = ""
        except RuntimeError as err:  # shape mismatches
            missing, unexpected, problem = [], [], str(err).splitlines()[1:3]
        missing = [k for k in missing if not k.startswith(head)]
        if missing or unexpected or problem:
            raise ConfigError(
                f"encoder weights file {weights!r} does not fit {model}: "
                f"missing {missing[:5]}, unexpected {unexpected[:5]} {problem}"
            )
        return
    name = weights if "." in weights or enum is None else f"{enum}.{weights}"
    try:
        found = models.get_weight(name) if "." in name else models.get_model_weights(model)[name]
    except (ValueError, KeyError, AttributeError) as err:
        raise ConfigError(
            f"unknown torchvision weights {weights!r} for {model}; use null, a name such as IMAGENET1K_V1, or a "
            "local file path"
        ) from err
    try:
        net.load_state_dict(found.get_state_dict(progress=False))
    except Exception as err:  # download failed (no network) or corrupt cache
        raise RuntimeError(
            f"could not load torchvision weights {name} ({err}). Without network access, download the file "
            f"elsewhere and pass its path as the encoder weights, or use weights=null (random init)."
        ) from err


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
        load_weights(net, weights, f"resnet{self.depth}", f"ResNet{self.depth}_Weights", ("fc.",))

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


class TorchvisionEncoder(nn.Module):
    """Any torchvision classification model up to its last spatial feature map: images ``[B, 3, H, W]`` ->
    ``[B, C, h, w]``. Per family: a ResNet (ResNeXt, Wide ResNet) up to its last stage; ConvNeXt,
    EfficientNet, MobileNet, VGG, DenseNet, MNASNet, SqueezeNet, AlexNet and Swin their ``features`` (Swin's
    channels-last output moved to channels first); RegNet its stem and trunk; a ViT its encoder's patch
    tokens (the class token dropped) laid out as the grid of patches. ``out_channels`` and
    ``feature_size(image_size)`` are measured by a forward pass of a blank image.

    Args:
        name: a torchvision classification model (``torchvision.models.list_models``), e.g. ``convnext_tiny``,
            ``efficientnet_b0``, ``regnet_y_400mf``, ``vit_b_16``.
        weights: ``None`` (random initialisation), a weights name of that model (``"DEFAULT"``,
            ``"IMAGENET1K_V1"``; downloaded by torchvision where there is internet) or a local state-dict file.
        image_size: the input size, given to the models whose layers depend on it (a ViT's position
            embedding); others take any size.
    """

    _SPATIAL = ("resnet", "resnext", "wide_resnet", "convnext", "efficientnet", "mobilenet", "vgg", "densenet",
                "mnasnet", "squeezenet", "alexnet", "swin", "regnet", "vit")  # fmt: skip

    def __init__(self, name: str, weights: str | None = None, image_size: int | None = None):
        super().__init__()
        from torchvision import models

        available = models.list_models(module=models)
        if name not in available:
            raise ConfigError(
                f"encoder.name={name!r} is no torchvision classification model; e.g. convnext_tiny, efficientnet_b0, "
                "regnet_y_400mf, vit_b_16 (torchvision.models.list_models())"
            )
        family = next((f for f in self._SPATIAL if name.startswith(f)), None)
        if family is None:
            raise ConfigError(f"encoder.name={name!r}: its feature map is not known here; families with one: "
                              f"{', '.join(self._SPATIAL)}")  # fmt: skip
        extra = {"image_size": int(image_size)} if family == "vit" and image_size is not None else {}
        net = models.get_model(name, weights=None, **extra)
        if weights is not None:
            head = ("fc.", "classifier.", "head.", "heads.")
            load_weights(net, str(weights), name, None, head)
        self.name, self.family = name, family
        if family in ("resnet", "resnext", "wide_resnet"):
            self.body = nn.Sequential(*list(net.children())[:-2])
        elif family == "regnet":
            self.body = nn.Sequential(net.stem, net.trunk_output)
        elif family == "vit":
            self.vit = net
            del net.heads
        else:
            self.body = net.features
        probe = (int(image_size),) * 2 if image_size is not None else (224, 224)
        channels, *size = self._probe(probe)
        self.out_channels = int(channels)
        self._sizes: dict[tuple[int, int], tuple[int, int]] = {probe: tuple(size)}  # the sizes measured

    @torch.no_grad()
    def _probe(self, size: tuple[int, int]) -> tuple[int, int, int]:
        """``(C, h, w)`` of the output for an input of ``size``, from a blank image in evaluation mode (no
        BatchNorm statistics move)."""
        modes = {m: m.training for m in self.modules()}
        self.eval()
        try:
            out = self(torch.zeros(1, 3, *size))
        finally:
            for m, training in modes.items():
                m.train(training)
        return tuple(out.shape[1:])

    def feature_size(self, image_size: int | tuple[int, int]) -> tuple[int, int]:
        """Spatial size of the output map for an input of ``image_size``."""
        size = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
        if size not in self._sizes:
            self._sizes[size] = tuple(self._probe(size)[1:])
        return self._sizes[size]

    def forward(self, images: torch.Tensor) -> torch.Tensor:
        if images.ndim != 4 or images.shape[1] != 3:
            raise ConfigError(f"images must have shape (batch, 3, H, W), got {tuple(images.shape)}")
        if self.family == "vit":
            vit = self.vit
            x = vit._process_input(images)  # [B, h*w, C] (it checks the image size)
            x = torch.cat([vit.class_token.expand(len(x), -1, -1), x], dim=1)
            x = vit.encoder(x)[:, 1:]  # the patch tokens  # [B, h*w, C]
            h, w = images.shape[2] // vit.patch_size, images.shape[3] // vit.patch_size
            return x.transpose(1, 2).reshape(len(x), -1, h, w)
        out = self.body(images)
        if self.family == "swin":  # channels last
            out = out.permute(0, 3, 1, 2)
        return out
