"""Image feature map -> signal on the sphere, in the Fourier domain (real SH, component normalisation).

Conventions
-----------
S2 points are e3nn YXY angles ``(alpha, beta)``, i.e. ``u = (sin b sin a, cos b, sin b cos a)``.
The image faces the ``+y`` pole: orthographic projection ``P(u) = (u_x, u_z)`` maps the
hemisphere ``beta <= pi/2`` onto the unit disk, whose horizontal image axis is ``x`` and vertical
image axis (rows, downwards) is ``z``. The feature map's pixel centres are placed on
``[-1, 1]^2``, so the image itself spans half a cell more on each side; the outermost grid point
lands at radius ``coverage``. Feature cells whose centre lies outside the image's inscribed circle
(the corners) are never read.
"""

from __future__ import annotations

import math

import torch
from e3nn import o3
from e3nn.nn import S2Activation
from torch import nn

from image2sphere.checks import ConfigError
from image2sphere.so3.grid import s2_healpix_grid
from image2sphere.so3.wigner import check_lmax, degree_scale, n_s2_coeffs

__all__ = ["HarmonicS2Projector", "SpatialS2Projector", "check_feature_size", "orthographic_interpolation"]


def check_feature_size(size) -> tuple[int, int]:
    """``(h, w)`` of a feature map size given as ``int`` or ``(h, w)``; ``ValueError`` unless both are >= 1."""
    h, w = (size, size) if isinstance(size, int) else tuple(size)
    if h < 1 or w < 1:
        raise ConfigError(f"feature map size must be positive, got {size!r}")
    return int(h), int(w)


def check_orthographic_args(coverage: float, sigma: float, taper_beta: float, max_beta: float) -> None:
    """``ValueError`` unless ``0 < coverage <= 1``, ``sigma > 0`` and ``0 < taper_beta <= max_beta <= pi``."""
    if not 0 < coverage <= 1:
        raise ConfigError(f"coverage must be in (0, 1], got {coverage!r}")
    if sigma <= 0:
        raise ConfigError(f"sigma must be positive, got {sigma!r}")
    if not 0 < taper_beta <= max_beta <= math.pi:
        raise ConfigError(f"need 0 < taper_beta <= max_beta <= pi, got {taper_beta!r}, {max_beta!r}")


def orthographic_interpolation(
    alpha: torch.Tensor,
    beta: torch.Tensor,
    feature_size: int | tuple[int, int],
    *,
    coverage: float = 0.9,
    sigma: float = 0.2,
    max_beta: float = math.pi / 2,
    taper_beta: float = math.radians(75),
    radius: float | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Read-out weights of sphere points ``(alpha, beta)`` ``[K]`` from an ``H x W`` feature map.

    Point ``u`` lands at ``P(u) = (u_x, u_z) * coverage / radius`` on the map's ``[-1, 1]^2`` (``radius``
    defaults to the largest ``|P(u)|`` of the points, so the outermost one lands at ``coverage``); its
    weights are Gaussian (``sigma``) over the feature cells whose centres lie inside the image's
    inscribed ellipse, normalised to sum to one, times the taper (1 up to ``taper_beta``, linearly
    down to 0 at ``max_beta``; points beyond ``max_beta`` get weight 0).

    Returns ``weight [H, W, K]`` and ``inside [H, W]`` (1 for the cells that are read), float64.
    """
    h, w = check_feature_size(feature_size)
    check_orthographic_args(coverage, sigma, taper_beta, max_beta)
    alpha, beta = torch.as_tensor(alpha, dtype=torch.float64), torch.as_tensor(beta, dtype=torch.float64)
    xyz = o3.angles_to_xyz(alpha, beta)  # [K, 3]
    planar = xyz[:, [0, 2]]  # (u_x, u_z): image (horizontal, vertical)
    planar = coverage * planar / (planar.norm(dim=1).max() if radius is None else radius)
    rows = torch.linspace(-1, 1, h, dtype=torch.float64) if h > 1 else torch.zeros(1, dtype=torch.float64)
    cols = torch.linspace(-1, 1, w, dtype=torch.float64) if w > 1 else torch.zeros(1, dtype=torch.float64)
    py, px = torch.meshgrid(rows, cols, indexing="ij")  # [H, W]
    # the image reaches half a cell beyond the outermost centres: its inscribed ellipse has these semi-axes
    rx, ry = 1 + 1 / max(w - 1, 1), 1 + 1 / max(h - 1, 1)
    inside = ((px / rx) ** 2 + (py / ry) ** 2 <= 1 + 1e-9).to(torch.float64)  # [H, W]
    d2 = (px[..., None] - planar[:, 0]) ** 2 + (py[..., None] - planar[:, 1]) ** 2  # [H, W, K]
    weight = torch.exp(-d2 / (2 * sigma**2)) * inside[..., None]
    weight = weight / weight.sum(dim=(0, 1), keepdim=True).clamp_min(1e-300)
    if taper_beta < max_beta:
        taper = ((max_beta - beta) / (max_beta - taper_beta)).clamp(0, 1)  # [K]
    else:
        taper = (beta <= max_beta + 1e-12).to(torch.float64)  # as s2_healpix_grid keeps its cap
    return weight * taper, inside


class SpatialS2Projector(nn.Module):
    """Orthographic projection of a feature map onto a HEALPix hemisphere, then the S2 Fourier transform.

    Each grid point ``u_i`` reads the (1x1-convolved) feature map at ``P(u_i)`` by Gaussian weights
    over the feature cells whose centres lie inside the image's inscribed circle (the corner cells
    are never read), normalised to sum to one, and scaled by a taper that falls
    linearly from 1 at ``taper_beta`` to 0 at ``max_beta``. With ``n_subset`` set, a random subset of
    that many grid points is used per training pass (all of them in eval mode, unless ``subset_in_eval``;
    the paper samples 20 in every forward pass, test included, as the original code does, but their
    coefficients are mostly sampling noise above degree 2, which stops I2S from learning at lmax 8 and
    10: docs/training_fidelity.md); with ``None``, every point, always. The Fourier
    coefficients are the discrete projection over the ``n`` points used,
    ``mean_i f(u_i) Y(u_i)`` (``normalization="mean"``, the default: an estimate of the same
    coefficients whatever ``n``, so a model trained on random subsets and evaluated on all points
    sees signals of the same size, and evaluation is deterministic) or ``sum_i f(u_i) Y(u_i) / sqrt(n)``
    (``"sqrt"``: coefficients ``sqrt(n)`` times larger, so ``sqrt(104 / 20) = 2.3`` times larger on all
    points of level 2 than on a training subset of 20).

    Input ``[B, in_channels, H, W]``; output ``[B, sphere_channels, (lmax+1)^2]``.
    """

    def __init__(
        self,
        in_channels: int,
        feature_size: int | tuple[int, int],
        sphere_channels: int = 512,
        lmax: int = 6,
        level: int = 2,
        max_beta: float = math.pi / 2,
        taper_beta: float = math.radians(75),
        coverage: float = 0.9,
        sigma: float = 0.2,
        n_subset: int | None = None,
        learn_interpolation: bool = True,
        activation: bool = True,
        normalization: str = "mean",
        subset_in_eval: bool = False,
    ):
        super().__init__()
        self.lmax = check_lmax(lmax)
        if not isinstance(subset_in_eval, bool):
            raise ConfigError(f"model.net.subset_in_eval must be true or false, got {subset_in_eval!r}")
        if subset_in_eval and n_subset is None:
            raise ConfigError("model.net.subset_in_eval=true needs model.net.n_subset (the number of points to draw)")
        self.subset_in_eval = subset_in_eval
        if normalization not in ("mean", "sqrt"):
            raise ConfigError(f"normalization must be 'mean' or 'sqrt', got {normalization!r}")
        self.normalization = normalization
        h, w = check_feature_size(feature_size)
        check_orthographic_args(coverage, sigma, taper_beta, max_beta)
        alpha, beta = s2_healpix_grid(level, max_beta=max_beta, dtype=torch.float64)  # [K]
        if n_subset is not None and not 1 <= n_subset <= len(alpha):
            raise ConfigError(f"n_subset must be in 1..{len(alpha)} (grid points at level {level}), got {n_subset!r}")
        self.n_subset = n_subset
        self.conv = nn.Conv2d(in_channels, sphere_channels, kernel_size=1)
        self.activation = activation

        weight, inside = orthographic_interpolation(
            alpha, beta, (h, w), coverage=coverage, sigma=sigma, max_beta=max_beta, taper_beta=taper_beta
        )  # [H, W, K], [H, W]
        self.register_buffer("inside", inside.to(torch.float32), persistent=False)  # [H, W]
        self.interpolation = nn.Parameter(weight.to(torch.float32), requires_grad=learn_interpolation)  # [H, W, K]
        self.register_buffer("alpha", alpha.float(), persistent=False)
        self.register_buffer("beta", beta.float(), persistent=False)
        Y = o3.spherical_harmonics_alpha_beta(list(range(lmax + 1)), alpha, beta, normalization="component")
        self.register_buffer("Y", Y.to(torch.float32), persistent=False)  # [K, (lmax+1)^2]

    @property
    def n_points(self) -> int:
        return self.Y.shape[0]

    def sample_points(self) -> torch.Tensor:
        """Indices of the grid points used by this forward pass: a random subset in training mode (and in
        eval mode too with ``subset_in_eval``)."""
        if (self.training or self.subset_in_eval) and self.n_subset is not None:
            return torch.randperm(self.n_points, device=self.Y.device)[: self.n_subset]
        return torch.arange(self.n_points, device=self.Y.device)

    def project(self, features: torch.Tensor, points: torch.Tensor | None = None) -> torch.Tensor:
        """Spatial signal on grid points ``points`` (default: all): ``[B, sphere_channels, len(points)]``."""
        if features.ndim != 4 or features.shape[-2:] != self.inside.shape:
            raise ConfigError(
                f"feature map must have shape (batch, channels, {self.inside.shape[0]}, {self.inside.shape[1]}), "
                f"got {tuple(features.shape)}"
            )
        points = torch.arange(self.n_points, device=self.Y.device) if points is None else points
        x = self.conv(features)  # [B, S, H, W]
        weight = self.interpolation[..., points] * self.inside[..., None]  # [H, W, k]
        signal = torch.einsum("bshw,hwk->bsk", x, weight)  # [B, S, k]
        return torch.relu(signal) if self.activation else signal

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        points = self.sample_points()
        signal = self.project(features, points)  # [B, S, k]
        n = len(points) if self.normalization == "mean" else math.sqrt(len(points))
        return torch.einsum("bsk,kj->bsj", signal, self.Y[points]) / n  # [B, S, (L+1)^2]


class HarmonicS2Projector(nn.Module):
    """ "Fourier projection": global average pool, then an MLP straight to S2 Fourier coefficients,
    then (``activation``) a ReLU on the sphere, as the spatial projection applies one to its samples.

    The ReLU is e3nn's ``S2Activation``: the signal on a grid of ``activation_resolution`` points in
    ``beta`` (default: 20, as the original code, or ``2 (lmax + 1) + 2`` where that is more), ReLU (scaled
    by e3nn to keep a unit normal's second moment, about sqrt 2), back to the coefficients up to
    ``lmax``. Its grids use e3nn's ``"norm"`` normalisation, which evaluates our component-normalised
    coefficients up to one constant for every degree (``"component"`` would weight degree ``l`` by
    ``1 / sqrt(2l + 1)``); the ReLU being positively homogeneous, the constant cancels on the way back.
    As the spatial projection's ReLU, it makes each channel a non-negative signal.

    ``degree_power``: the MLP's outputs of degree ``l`` are multiplied by ``(2l+1)^-degree_power``, a
    reparametrisation (the first signal is the same, the weights drawn larger by what the scale takes).
    An optimiser step of the same size in every weight (Adam's) changes each coefficient's share of the
    signal alike, so degree ``l`` takes a share ``2l+1`` of every step with ``0`` (the default, the
    original code's); ``0.5`` gives every degree the same share, as :class:`~image2sphere.nn.FourierMLP`'s
    ``degree_power=1`` does for SO(3). Measured with one seed, 0.5 helped the Fourier filter and hurt the
    spatial filter (docs/training_fidelity.md, "The Fourier basis with an MLP").

    Input ``[B, in_channels, H, W]``; output ``[B, sphere_channels, (lmax+1)^2]``.
    """

    def __init__(
        self,
        in_channels: int,
        sphere_channels: int = 64,
        lmax: int = 6,
        hidden_channels: int = 512,
        activation: bool = True,
        activation_resolution: int | None = None,
        degree_power: float = 0.0,
    ):
        super().__init__()
        self.lmax = check_lmax(lmax)
        self.sphere_channels = sphere_channels
        l = torch.arange(self.lmax + 1)
        degrees = torch.repeat_interleave(l, 2 * l + 1)  # [(L+1)^2]: the degree of each S2 coefficient
        self.register_buffer("degree_scale", degree_scale(degrees, degree_power), persistent=False)
        last = nn.Linear(hidden_channels, sphere_channels * n_s2_coeffs(lmax))
        # each channel's S2 signal (mean square = sum of its (lmax+1)^2 coefficients squared) starts at
        # about the size the spatial projector gives, not (lmax+1)^2 times larger
        nn.init.normal_(last.weight, std=1 / math.sqrt(hidden_channels * n_s2_coeffs(lmax)))
        nn.init.zeros_(last.bias)
        with torch.no_grad():  # the same first signal whatever degree_power is
            last.weight.view(sphere_channels, n_s2_coeffs(lmax), hidden_channels).div_(self.degree_scale[:, None])
        self.mlp = nn.Sequential(nn.Linear(in_channels, hidden_channels), nn.ReLU(), last)
        # degree l has parity (-1)^l, as a function on the sphere
        irreps = o3.Irreps.spherical_harmonics(lmax, p=-1)
        res = max(20, 2 * (lmax + 1) + 2) if activation_resolution is None else activation_resolution
        self.act = S2Activation(irreps, torch.relu, res, normalization="norm") if activation else nn.Identity()

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if features.ndim != 4:
            raise ConfigError(f"feature map must have shape (batch, channels, H, W), got {tuple(features.shape)}")
        pooled = features.mean(dim=(-1, -2))  # [B, C]
        coeffs = self.mlp(pooled).view(len(features), self.sphere_channels, n_s2_coeffs(self.lmax))
        coeffs = coeffs * self.degree_scale  # [B, S, (L+1)^2]
        return self.act(coeffs)  # [B, S, (L+1)^2]
