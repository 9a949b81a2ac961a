"""Direct Wigner-D regression (Lee & Cho, "3D Equivariant Pose Regression via Direct Wigner-D
Harmonics Prediction", NeurIPS 2024): I2S's network trained to output the Wigner-D matrices of the
label.

Conventions (docs/conventions.md#flat-wigner-layout)
----------------------------------------------------
* The network is I2S's (:class:`~image2sphere.nn.I2S`: encoder, projection onto S2, S2 and SO(3)
  convolutions), whose output is SO(3) Fourier coefficients ``c`` ``(B, n_so3_coeffs(lmax))`` in the
  flat Wigner layout.
* The target of a rotation ``R`` is its Wigner-D matrices, ``D^l(R) = e3nn.o3.wigner_D(l, angles(R))``
  for ``l = 0..lmax``, flattened row-major and concatenated (:func:`wigner_target`). Read as
  coefficients, the target is the band-limited delta at ``R``: the signal
  ``f(g) = sum_l sqrt(2l+1) tr(D^l(R)^T D^l(g)) = sum_l sqrt(2l+1) chi_l(R^-1 g)`` peaks at ``g = R``.
* The regression loss is the mean squared error over the coefficients, ``mean_i (c_i - D_i(R))^2``
  (:func:`wigner_mse`). It is equivariant: left-translating the prediction by ``g``
  (``c^l -> D^l(g) c^l``) and the label (``R -> g R``) leaves it unchanged, since ``D^l`` is orthogonal.
  It is **not** invariant to the choice among a symmetric object's equivalent rotations
  (``D(R S) != D(R)``): a single regressed rotation cannot represent a symmetry, which is why the
  paper adds I2S's distribution loss for symmetric objects (``distribution_weight``). Averaged over the
  whole equivalence set (``dataset.label=all``) the loss is the same whichever rotation of the set is
  called the label.
* The prediction is the distribution I2S's output stands for: the softmax of the signal on the
  HEALPix grid (:class:`~image2sphere.distributions.fourier.SO3Distribution`); its mode is the grid
  argmax of the predicted band-limited delta, and the recalibration's temperature sets its spread.
"""

from __future__ import annotations

import math

import torch

from image2sphere.checks import ConfigError
from image2sphere.distributions.fourier import fourier_grid_nll, fourier_grid_set_nll
from image2sphere.nn.i2s import I2S
from image2sphere.rotation_sets import check_rotation_set, fill_padding
from image2sphere.so3.wigner import check_lmax, flat_wigner, so3_layout

__all__ = ["WignerDRegression", "wigner_mse", "wigner_target"]


def wigner_target(lmax: int, rotations: torch.Tensor) -> torch.Tensor:
    """The Wigner-D matrices ``D^l(R)`` of rotations ``(..., 3, 3)`` for ``l = 0..lmax``, flattened
    row-major and concatenated: ``(..., n_so3_coeffs(lmax))`` (the flat layout without its
    ``sqrt(2l+1)`` factors)."""
    lmax = check_lmax(lmax)
    degrees = so3_layout(lmax)[0].to(device=rotations.device)
    scale = (2 * degrees + 1).to(rotations.dtype).sqrt()  # [n]
    return flat_wigner(lmax, rotations) / scale


def wigner_mse(coeffs: torch.Tensor, target: torch.Tensor) -> torch.Tensor:
    """Mean squared error over the coefficients (last dimension): ``(...)``."""
    if coeffs.shape[-1] != target.shape[-1]:
        raise ConfigError(f"coefficients {tuple(coeffs.shape)} and target {tuple(target.shape)} differ in size")
    return (coeffs - target).square().mean(-1)


class WignerDRegression(I2S):
    """I2S's network (every argument of :class:`~image2sphere.nn.I2S`) trained by direct Wigner-D
    regression (module docstring).

    Args:
        regression_weight: weight of the Wigner-D mean squared error (> 0).
        distribution_weight: weight of I2S's grid cross-entropy added to it (>= 0; ``0``: the
            regression alone, the paper's loss for objects without symmetry).
        **kwargs: the arguments of :class:`~image2sphere.nn.I2S`.
    """

    def __init__(self, *args, regression_weight: float = 1.0, distribution_weight: float = 0.0, **kwargs):
        super().__init__(*args, **kwargs)
        for name, value, low in (("regression_weight", regression_weight, 0.0),
                                 ("distribution_weight", distribution_weight, 0.0)):  # fmt: skip
            ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
            if not ok or value < low or (name == "regression_weight" and value == 0):
                limit = "> 0" if name == "regression_weight" else ">= 0"
                raise ConfigError(f"model.net.{name} must be a finite number {limit}, got {value!r}")
        self.regression_weight = float(regression_weight)
        self.distribution_weight = float(distribution_weight)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """``regression_weight * MSE(c, D(R)) + distribution_weight * I2S's cross-entropy``, ``(B,)``."""
        target = wigner_target(self.lmax, rotation.detach().to(output))  # [B, n]
        loss = self.regression_weight * wigner_mse(output, target)
        if self.distribution_weight:
            loss = loss + self.distribution_weight * fourier_grid_nll(output, self.lmax, rotation, grid_level)
        return loss

    def set_loss(
        self, output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor, grid_level: int
    ) -> torch.Tensor:
        """:meth:`loss` averaged over each image's equivalent ``rotations (B, M, 3, 3)`` where ``mask (B, M)``:
        the targets of the whole set at once (and one grid normaliser per image)."""
        check_rotation_set(output, rotations, mask)
        real = mask.to(output)
        target = wigner_target(self.lmax, fill_padding(rotations, mask).detach().to(output))  # [B, M, n]
        mse = (wigner_mse(output[:, None], target) * real).sum(1) / real.sum(1)  # [B]
        loss = self.regression_weight * mse
        if self.distribution_weight:
            nll = fourier_grid_set_nll(output, self.lmax, rotations, mask, grid_level)
            loss = loss + self.distribution_weight * nll
        return loss
