"""The Image2Sphere network and the "Fourier basis with MLP" baseline.

Both map images ``[B, 3, H, W]`` (and, optionally, class indices ``[B]``) to the Fourier
coefficients ``[B, n_so3_coeffs(lmax)]`` of an SO(3) signal in the flat Wigner layout; the signal
on an SO(3) grid, put through a softmax, is the predicted distribution
(:class:`image2sphere.distributions.fourier.SO3Distribution`). Every choice is a constructor argument, so Hydra
builds any variant of the paper's ablations from configuration.
"""

from __future__ import annotations

import math

import torch
from torch import nn

from image2sphere.checks import ConfigError
from image2sphere.distributions.fourier import SO3Distribution, fourier_grid_nll, fourier_grid_set_nll
from image2sphere.nn.activation import SO3ReLU
from image2sphere.nn.base import PoseNetwork
from image2sphere.nn.projector import HarmonicS2Projector, SpatialS2Projector
from image2sphere.nn.s2_conv import INITS, S2Conv
from image2sphere.nn.so3_conv import SO3Conv
from image2sphere.so3.grid import so3_tube_grid
from image2sphere.so3.wigner import check_lmax, degree_scale, n_so3_coeffs, so3_layout

__all__ = ["I2S", "FourierMLP"]

PROJECTORS = ("spatial", "harmonic")
SO3_KERNELS = ("local", "tube")
OUTPUT_INITS = ("zero", "random")


class _FourierNetwork(PoseNetwork):
    """A network whose output is the Fourier coefficients of the log density's signal: trained as a
    classifier over the SO(3) grid (cross-entropy at the point nearest the label)."""

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int],
        lmax: int,
        num_classes: int,
        input_scaling: str = "imagenet",
    ):
        super().__init__(encoder, image_size, num_classes, input_scaling)
        self.lmax = check_lmax(lmax)

    def output_distribution(self, output: torch.Tensor) -> SO3Distribution:
        return SO3Distribution(output, self.lmax)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """Cross-entropy ``(B,)`` against the grid point of ``grid_level`` nearest each label."""
        return fourier_grid_nll(output, self.lmax, rotation, grid_level)

    def set_loss(
        self, output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor, grid_level: int
    ) -> torch.Tensor:
        """:meth:`loss` averaged over each image's equivalent rotations ``(B,)``, one normaliser per image."""
        return fourier_grid_set_nll(output, self.lmax, rotations, mask, grid_level)


class I2S(_FourierNetwork):
    """Image2Sphere: encoder -> projection onto S2 -> S2 conv -> (SO(3) ReLU -> SO(3) conv) x n.

    Args:
        encoder: a module with ``out_channels``, ``feature_size(image_size)`` and ``forward``
            (e.g. :class:`image2sphere.nn.ResNetEncoder`).
        image_size: input image size (224 in the paper; 7x7 feature map).
        lmax: band limit of every Fourier representation (6).
        projector: ``"spatial"`` (orthographic projection, I2S) or ``"harmonic"`` (MLP to SH
            coefficients, the "Fourier projection" ablation).
        filter: the S2 filter's parametrisation, ``"harmonic"`` (I2S) or ``"spatial"``.
        sphere_channels: channels of the S2 signal (after the projector's 1x1 convolution).
        so3_channels: channels of the hidden SO(3) signal (8 in the paper).
        n_so3_conv: 0, 1 (I2S) or 2 SO(3) convolutions after the S2 convolution.
        projector_level, n_subset, taper_deg, coverage, sigma: the spatial projector's HEALPix
            level (2), points used per training pass (``None``: all, as at test; the paper samples
            20, whose coefficients are mostly sampling noise above degree 2 and stop training at
            lmax 8 and 10, docs/training_fidelity.md), taper start (75 deg), disk coverage (0.9) and
            Gaussian width (0.2, in units of half the map).
        subset_in_eval: draw the ``n_subset`` random points in evaluation too, as the original code's
            every forward pass does (the paper: "20 points are randomly selected during each forward
            pass"); each evaluation of an image is then a random draw. ``False``: every point at test.
        harmonic_hidden: hidden width of the harmonic projector's MLP.
        harmonic_degree_power: the harmonic projector's ``degree_power`` (0: its coefficients as they
            come; 0.5: every degree an equal share of an optimiser step;
            :class:`~image2sphere.nn.HarmonicS2Projector`).
        s2_kernel_level: HEALPix level of the spatial S2 filter's points.
        so3_kernel_max_deg: support of the SO(3) filter around the identity (22.5 deg).
        activation_resolution: resolution of e3nn's SO(3) grid for the ReLU; ``None``:
            ``max(8, lmax + 2)``, one degree to spare above the band limit
            (:class:`~image2sphere.nn.SO3ReLU`).
        num_classes: if > 0, the class one-hot is appended to the feature map as constant channels.
        init: initialisation of the S2 and SO(3) convolutions, ``"unit"`` (N(0, 1) parameters scaled
            in the forward pass), ``"fan_in"`` (parameters at the scale that keeps the signal's size,
            as ``nn.Linear``) or ``"kaiming_uniform"`` (the original code's: the S2 filter drawn by
            ``torch.nn.init.kaiming_uniform_``, std 0.071 at 8 output channels and lmax 6, scaled by
            ``1 / sqrt(sphere_channels)``; the SO(3) convolutions as ``"unit"``); see
            :mod:`image2sphere.nn.s2_conv`.
        projector_normalization: ``"mean"`` (coefficients independent of the number of projection
            points) or ``"sqrt"``; see :class:`~image2sphere.nn.SpatialS2Projector`.
        so3_kernel: support of the SO(3) filter, ``"local"`` (rotations within ``so3_kernel_max_deg``
            of the identity, as the paper describes) or ``"tube"`` (the original code's grid, see
            :func:`~image2sphere.so3.so3_tube_grid`).
        output_init: ``"zero"``: the last convolution (the last SO(3) convolution, or the S2
            convolution when there is none) starts at zero, so the first prediction is exactly
            uniform while every earlier layer carries its full signal; ``"random"``: drawn like the
            others (the original code), whose random logits start the loss above uniform, and whose
            first steps then go into shrinking that random output: at lmax 8 the loss stayed at
            uniform for 80 of the first epoch's 144 steps (docs/training_fidelity.md, "The band limit").
        input_scaling: what the encoder sees: ``"imagenet"``, the ImageNet-normalised images the data
            pipeline gives (what torchvision's pretrained weights expect), or ``"unit"``, those mapped
            back to ``pixels / 255`` (the original code's input); see :mod:`image2sphere.nn.base`.
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        lmax: int = 6,
        projector: str = "spatial",
        filter: str = "harmonic",
        sphere_channels: int = 512,
        so3_channels: int = 8,
        n_so3_conv: int = 1,
        projector_level: int = 2,
        n_subset: int | None = None,
        taper_deg: float = 75.0,
        coverage: float = 0.9,
        sigma: float = 0.2,
        harmonic_hidden: int = 512,
        harmonic_degree_power: float = 0.0,
        s2_kernel_level: int = 2,
        so3_kernel_max_deg: float = 22.5,
        activation_resolution: int | None = None,
        num_classes: int = 0,
        init: str = "unit",
        projector_normalization: str = "mean",
        so3_kernel: str = "local",
        output_init: str = "zero",
        input_scaling: str = "imagenet",
        subset_in_eval: bool = False,
    ):
        super().__init__(encoder, image_size, lmax, num_classes, input_scaling)
        if output_init not in OUTPUT_INITS:
            raise ConfigError(f"output_init must be one of {OUTPUT_INITS}, got {output_init!r}")
        if init not in INITS:
            raise ConfigError(
                f"model.net.init must be one of {INITS}, got {init!r}: 'unit' (the default), 'fan_in', or "
                "'kaiming_uniform' (the original code's S2 filter draw)"
            )
        if so3_kernel not in SO3_KERNELS:
            raise ConfigError(f"so3_kernel must be one of {SO3_KERNELS}, got {so3_kernel!r}")
        if projector not in PROJECTORS:
            raise ConfigError(f"projector must be one of {PROJECTORS}, got {projector!r}")
        if n_so3_conv not in (0, 1, 2):
            raise ConfigError(f"n_so3_conv must be 0, 1 or 2, got {n_so3_conv!r}")
        if projector == "spatial":
            self.projector = SpatialS2Projector(
                self.feature_channels,
                self.feature_size,
                sphere_channels=sphere_channels,
                lmax=lmax,
                level=projector_level,
                taper_beta=math.radians(taper_deg),
                coverage=coverage,
                sigma=sigma,
                n_subset=n_subset,
                normalization=projector_normalization,
                subset_in_eval=subset_in_eval,
            )
        else:
            self.projector = HarmonicS2Projector(
                self.feature_channels,
                sphere_channels=sphere_channels,
                lmax=lmax,
                hidden_channels=harmonic_hidden,
                degree_power=harmonic_degree_power,
            )
        s2_out = so3_channels if n_so3_conv > 0 else 1
        self.s2_conv = S2Conv(
            sphere_channels, s2_out, lmax=lmax, filter=filter, kernel_level=s2_kernel_level, init=init
        )
        max_angle = math.radians(so3_kernel_max_deg)
        kernel = so3_tube_grid(max_angle, dtype=torch.float64) if so3_kernel == "tube" else None
        layers: list[nn.Module] = []
        for i in range(n_so3_conv):
            out = 1 if i == n_so3_conv - 1 else so3_channels
            layers += [
                SO3ReLU(lmax, activation_resolution),
                SO3Conv(so3_channels, out, lmax=lmax, max_angle=max_angle, kernel=kernel, init=init),
            ]
        self.so3_layers = nn.Sequential(*layers)
        if output_init == "zero":
            nn.init.zeros_(self.output_layer.weight)

    @property
    def output_layer(self) -> nn.Module:
        """The convolution that gives the output: the last SO(3) convolution, or the S2 one if there is none."""
        return self.so3_layers[-1] if len(self.so3_layers) else self.s2_conv

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` -> SO(3) coefficients ``[B, n_so3_coeffs(lmax)]``."""
        x = self.projector(self.features(images, class_index))  # [B, S, (L+1)^2]
        x = self.s2_conv(x)  # [B, so3_channels, n_so3]
        x = self.so3_layers(x)  # [B, 1, n_so3]
        return x.squeeze(1)


class FourierMLP(_FourierNetwork):
    """Baseline "Fourier basis w/ MLP": pooled encoder features -> MLP -> SO(3) coefficients.

    Args:
        hidden: widths of the hidden layers.
        output_init: ``"zero"``: the last layer starts at zero (the first prediction is uniform), as
            I2S's last convolution; ``"random"``: drawn so that the first logits have about unit variance.
        degree_power: the last layer's outputs of degree ``l`` are multiplied by ``(2l+1)^-degree_power``
            (a reparametrisation: the same functions are reachable). ``0``: every coefficient as it
            comes. An optimiser step of the same size in every weight (Adam's) changes the logits by
            the same mean square per coefficient, so degree ``l`` gets a share ``(2l+1)^2`` of every
            step, most of it in degrees whose gradient is noise; ``1`` gives every degree the same share.
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        lmax: int = 6,
        hidden: tuple[int, ...] | list[int] = (512,),
        num_classes: int = 0,
        output_init: str = "zero",
        degree_power: float = 1.0,
    ):
        super().__init__(encoder, image_size, lmax, num_classes)
        if output_init not in OUTPUT_INITS:
            raise ConfigError(f"output_init must be one of {OUTPUT_INITS}, got {output_init!r}")
        self.register_buffer("degree_scale", degree_scale(so3_layout(self.lmax)[0], degree_power), persistent=False)
        widths = [self.feature_channels, *hidden]
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:], strict=True):
            layers += [nn.Linear(a, b), nn.ReLU()]
        last = nn.Linear(widths[-1], n_so3_coeffs(lmax))
        # The signal f(R) = sum_l sqrt(2l+1) sum_mn c^l_mn D^l_mn(R) of iid coefficients of variance v has
        # variance v * n_so3_coeffs: scale the last layer (after a ReLU: Kaiming's gain 2 when hidden)
        # so that the initial logits have about unit variance and the first loss is close to uniform's.
        gain = 2.0 if hidden else 1.0
        if output_init == "random":
            nn.init.normal_(last.weight, std=math.sqrt(gain / widths[-1] / n_so3_coeffs(lmax)))
            with torch.no_grad():  # the same first logits whatever degree_power is
                last.weight.div_(self.degree_scale[:, None])
        else:
            nn.init.zeros_(last.weight)
        nn.init.zeros_(last.bias)
        layers.append(last)
        self.mlp = nn.Sequential(*layers)

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` -> SO(3) coefficients ``[B, n_so3_coeffs(lmax)]``."""
        return self.mlp(self.pooled_features(images, class_index)) * self.degree_scale  # [B, C] -> [B, n_so3]
