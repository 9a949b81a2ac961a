"""Image2Sphere over the icosahedral group: the "Icosahedral group version" of the I2S paper's Table 4.

The I2S pipeline with the S2 and SO(3) convolutions replaced by group convolutions over the 60
rotations of the icosahedral group ``I``, and continuous predictions by anchor regression as in
Chen et al. 2021, "Equivariant point network for 3D point cloud analysis" (EPN, CVPR): the 60 group
elements are the anchors; the network gives a logit and a residual rotation per anchor, and the
prediction is ``A_k @ exp([r_k]_x)`` for the anchor ``k`` of largest logit.

Pipeline (shapes for a batch ``B``; ``n`` points of the sphere, 60 group elements)::

    features [B, C, h, w] -> PointSetProjector [B, S, n] -> IcosahedralLifting [B, c, 60]
        -> (ReLU -> IcosahedralGroupConv) x n_group_conv -> [B, 4, 60]: a logit and a residual per anchor

Conventions
-----------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; sphere points are unit vectors ``(n, 3)``,
  in e3nn's frame (the image faces ``+y``, :mod:`image2sphere.nn.projector`).
* The group ``G`` (:func:`icosahedral_group`): 60 matrices ``G[g]`` ``(60, 3, 3)`` float64 from
  ``scipy.spatial.transform.Rotation.create_group("I")``
  (:func:`~image2sphere.so3.groups.rotation_group` with ``sort=True``), identity first, the others
  in a fixed (lexicographic) order. ``cayley[g, h]`` is the index of ``G[g] @ G[h]`` and
  ``inverse[g]`` that of ``G[g]^T``, both found by nearest match, exact to ``1e-6``.
* The point set ``P`` (:func:`icosahedral_points`): the 12 vertices, 20 face centres and 30 edge
  midpoints of the icosahedron (the 5-, 3- and 2-fold axes) and ``n_orbits`` generic orbits of 60
  points. ``P`` is closed under ``G``: ``action[g, p]`` (:func:`point_action`) is the index of
  ``G[g] @ P[p]``, a permutation of the points for each ``g``.
* Signals: on the points ``[..., n]``, on the group ``[..., 60]`` (channels before). A rotation
  ``h`` acts on them by ``(h Phi)(p) = Phi(h^-1 p)`` (:func:`rotate_point_signal`) and
  ``(h f)(g) = f(h^-1 g)`` (:func:`translate_group_signal`).
* Lifting (:class:`IcosahedralLifting`): ``f(g) = sum_p psi(g^-1 p) Phi(p)``. Group convolution
  (:class:`IcosahedralGroupConv`): ``f'(g) = sum_k psi(k^-1 g) f(k)``. Both filters have full support
  (every point, every group element). ReLU acts pointwise on the group. So an input ``h Phi`` gives
  the output ``h f``, exactly.
* Anchor regression: the output ``[B, 4, 60]`` is, per anchor ``k = G[k]``, a logit (channel 0) and
  an axis-angle residual ``r_k`` (channels 1..3) in the anchor's own frame. The prediction is
  ``R = G[k*] @ exp([r_k*]_x)`` with ``k* = argmax`` of the logits. As the output transforms as
  ``h f``, the input ``h Phi`` moves ``k*`` to the index of ``h @ G[k*]`` with the same residual, and
  the prediction to ``h @ R``.
* Loss per image: the cross-entropy of the logits against the anchor nearest the label, plus
  ``residual_weight`` times the rotation loss (geodesic angle, whose ``acos`` keeps gradients finite
  at 0, or squared Frobenius distance) of that anchor's corrected rotation against the label.
* The output's distribution is a :class:`~image2sphere.distributions.base.PointEstimate` (no
  density: log likelihood and spread are reported as not available).
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F
from e3nn import o3
from torch import nn

from image2sphere.checks import ConfigError, check_int, check_number
from image2sphere.distributions.base import PointEstimate
from image2sphere.nn.base import PoseNetwork
from image2sphere.nn.projector import check_feature_size, orthographic_interpolation
from image2sphere.so3.groups import rotation_group
from image2sphere.so3.rotations import geodesic_distance, rotvec_to_matrix

__all__ = [
    "GROUP_ORDER",
    "IcosahedralGroup",
    "IcosahedralGroupConv",
    "IcosahedralI2S",
    "IcosahedralLifting",
    "PointSetProjector",
    "icosahedral_group",
    "icosahedral_points",
    "point_action",
    "rotate_point_signal",
    "translate_group_signal",
]

GROUP_ORDER = 60
#: barycentric weights (5-fold, 3-fold, 2-fold axis) of the base points of the generic orbits, each
#: inside one (2, 3, 5) triangle, so with a trivial stabiliser: 60 distinct points per orbit
ORBIT_WEIGHTS = ((2.0, 1.0, 1.0), (1.0, 2.0, 1.0), (1.0, 1.0, 2.0))
MATCH_TOL = 1e-6
ROTATION_LOSSES = ("geodesic", "frobenius")


# ---------------------------------------------------------------------------------------------- the group
def _match(queries: np.ndarray, targets: np.ndarray, what: str) -> np.ndarray:
    """Index ``(N,)`` of the target ``(M, ...)`` equal to each query ``(N, ...)``: the nearest one, which
    must agree to ``MATCH_TOL`` in every entry (``AssertionError`` otherwise)."""
    diff = np.abs(queries[:, None] - targets[None]).reshape(len(queries), len(targets), -1).max(-1)  # [N, M]
    index = diff.argmin(axis=1)
    worst = diff[np.arange(len(queries)), index].max() if len(queries) else 0.0
    assert worst < MATCH_TOL, f"{what}: no exact match (off by {worst:.3g})"
    return index


@functools.cache
def _icosahedral_tables() -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    G = rotation_group("I", sort=True).numpy()  # [60, 3, 3], identity first, then lexicographic
    if G.shape != (GROUP_ORDER, 3, 3):
        raise RuntimeError(f"scipy's icosahedral group has shape {G.shape}, expected (60, 3, 3)")
    products = np.einsum("gij,hjk->ghik", G, G).reshape(-1, 3, 3)  # [60 * 60, 3, 3]
    cayley = _match(products, G, "G[g] @ G[h]").reshape(GROUP_ORDER, GROUP_ORDER)
    inverse = _match(G.transpose(0, 2, 1), G, "G[g]^T")
    return G, cayley, inverse


@dataclass(frozen=True)
class IcosahedralGroup:
    """The 60 rotations of the icosahedral group and their multiplication.

    Attributes:
        matrices: ``(60, 3, 3)`` float64, ``matrices[0]`` the identity.
        cayley: ``(60, 60)`` long, ``cayley[g, h]`` the index of ``matrices[g] @ matrices[h]``.
        inverse: ``(60,)`` long, ``inverse[g]`` the index of ``matrices[g]^T``.
    """

    matrices: torch.Tensor
    cayley: torch.Tensor
    inverse: torch.Tensor


def icosahedral_group() -> IcosahedralGroup:
    """The icosahedral rotation group (module docstring); fresh tensors on each call."""
    G, cayley, inverse = _icosahedral_tables()
    return IcosahedralGroup(
        torch.from_numpy(G.copy()), torch.from_numpy(cayley.copy()), torch.from_numpy(inverse.copy())
    )


def _unique_points(points: np.ndarray) -> np.ndarray:
    """The distinct unit vectors of ``points (N, 3)`` (first occurrences, to ``MATCH_TOL``), sorted."""
    kept: list[np.ndarray] = []
    for p in points:
        if not kept or np.abs(np.asarray(kept) - p).max(1).min() > MATCH_TOL:
            kept.append(p)
    kept_array = np.asarray(kept)
    return kept_array[np.lexsort(np.round(kept_array, 9).T[::-1])]


@functools.cache
def _points_np(n_orbits: int) -> np.ndarray:
    from scipy.spatial.transform import Rotation

    G, _, _ = _icosahedral_tables()
    rotvec = Rotation.from_matrix(G[1:]).as_rotvec()  # [59, 3]
    angle = np.linalg.norm(rotvec, axis=1)
    axis = rotvec / angle[:, None]
    fold = np.rint(2 * np.pi / np.where(np.isclose(angle, 4 * np.pi / 5), 2 * np.pi / 5, angle)).astype(int)
    axes = {k: _unique_points(np.concatenate([axis[fold == k], -axis[fold == k]])) for k in (5, 3, 2)}
    assert [len(axes[k]) for k in (5, 3, 2)] == [12, 20, 30], "icosahedral axes: expected 12, 20 and 30 points"
    # one (2, 3, 5) triangle: the 5-fold axis nearest a fixed generic direction d, a 3-fold axis nearest
    # to it, a 2-fold axis nearest to both (d breaks the exact ties among 5 faces and among 2 edges)
    d = np.array([0.3, 1.0, 0.2])
    v = axes[5][np.argmax(axes[5] @ d)]
    f = axes[3][np.argmax(axes[3] @ v + 1e-6 * axes[3] @ d)]
    e = axes[2][np.argmax(axes[2] @ (v + f) + 1e-6 * axes[2] @ d)]
    assert np.isclose(v @ f, np.cos(np.arctan(3 - 5**0.5))), "not a (2, 3, 5) triangle"
    orbits = []
    for weights in ORBIT_WEIGHTS[:n_orbits]:
        base = weights[0] * v + weights[1] * f + weights[2] * e
        orbits.append(G @ (base / np.linalg.norm(base)))  # [60, 3]
    points = np.concatenate([axes[5], axes[3], axes[2], *orbits])
    assert len(_unique_points(points)) == len(points) == 62 + 60 * n_orbits, "the orbits overlap"
    return points


def icosahedral_points(n_orbits: int = 2) -> torch.Tensor:
    """Unit vectors ``(62 + 60 n_orbits, 3)`` float64 closed under the icosahedral group: the 12
    vertices, 20 face centres and 30 edge midpoints of the icosahedron, then ``n_orbits`` (0 to 3)
    orbits of 60 points (``G[g] @ base`` in the group's order) of base points inside one (2, 3, 5)
    triangle."""
    if isinstance(n_orbits, bool) or not isinstance(n_orbits, int) or not 0 <= n_orbits <= len(ORBIT_WEIGHTS):
        raise ConfigError(f"n_orbits must be an integer in 0..{len(ORBIT_WEIGHTS)}, got {n_orbits!r}")
    return torch.from_numpy(_points_np(n_orbits).copy())


def point_action(points: torch.Tensor) -> torch.Tensor:
    """``action (60, n)`` long: ``action[g, p]`` is the index of ``G[g] @ points[p]`` among
    ``points (n, 3)``, which must be closed under the group (``AssertionError`` otherwise)."""
    if points.ndim != 2 or points.shape[1] != 3:
        raise ConfigError(f"points must have shape (n, 3), got {tuple(points.shape)}")
    G, _, _ = _icosahedral_tables()
    P = points.detach().cpu().double().numpy()
    moved = np.einsum("gij,pj->gpi", G, P).reshape(-1, 3)  # [60 * n, 3]
    return torch.from_numpy(_match(moved, P, "G[g] @ P[p]").reshape(GROUP_ORDER, len(P)))


def rotate_point_signal(signal: torch.Tensor, h: int, action: torch.Tensor) -> torch.Tensor:
    """``(h Phi)(p) = Phi(h^-1 p)`` for a signal ``[..., n]`` on the points of ``action (60, n)``."""
    inverse = icosahedral_group().inverse
    return signal[..., action[inverse[h]].to(signal.device)]


def translate_group_signal(signal: torch.Tensor, h: int) -> torch.Tensor:
    """``(h f)(g) = f(h^-1 g)`` for a signal ``[..., 60]`` on the group."""
    group = icosahedral_group()
    return signal[..., group.cayley[group.inverse[h]].to(signal.device)]


# ---------------------------------------------------------------------------------------------- layers
class PointSetProjector(nn.Module):
    """Orthographic projection of a feature map onto a point set of the sphere (I2S's spatial
    projector, :class:`~image2sphere.nn.SpatialS2Projector`, on other points and without the Fourier
    transform).

    A 1x1 convolution to ``sphere_channels``, then each visible point (``beta < max_beta``, the
    hemisphere facing the image) reads the map by the learned interpolation weights
    (:func:`~image2sphere.nn.projector.orthographic_interpolation`, the sphere's rim at ``coverage``),
    then a ReLU; the hidden points get 0.

    Input ``[B, in_channels, H, W]``; output ``[B, sphere_channels, n]``.
    """

    def __init__(
        self,
        in_channels: int,
        feature_size: int | tuple[int, int],
        points: torch.Tensor,
        sphere_channels: int = 512,
        max_beta: float = math.pi / 2,
        taper_beta: float = math.radians(75),
        coverage: float = 0.9,
        sigma: float = 0.2,
    ):
        super().__init__()
        if points.ndim != 2 or points.shape[1] != 3:
            raise ConfigError(f"points must have shape (n, 3), got {tuple(points.shape)}")
        h, w = check_feature_size(feature_size)
        alpha, beta = o3.xyz_to_angles(points.double())  # [n] each
        visible = torch.nonzero(beta < max_beta - 1e-9).flatten()  # [k]
        if len(visible) == 0:
            raise ConfigError("no point of the set lies on the hemisphere facing the image")
        weight, inside = orthographic_interpolation(
            alpha[visible], beta[visible], (h, w), coverage=coverage, sigma=sigma, max_beta=max_beta,
            taper_beta=taper_beta, radius=1.0,
        )  # fmt: skip
        self.n_points = len(points)
        self.conv = nn.Conv2d(in_channels, sphere_channels, kernel_size=1)
        self.register_buffer("visible", visible, persistent=False)  # [k]
        self.register_buffer("inside", inside.to(torch.float32), persistent=False)  # [H, W]
        self.interpolation = nn.Parameter(weight.to(torch.float32))  # [H, W, k]

    def forward(self, features: torch.Tensor) -> torch.Tensor:
        if features.ndim != 4 or features.shape[-2:] != self.inside.shape:
            raise ConfigError(
                f"feature map must have shape (batch, channels, {self.inside.shape[0]}, {self.inside.shape[1]}), "
                f"got {tuple(features.shape)}"
            )
        x = self.conv(features)  # [B, S, H, W]
        weight = self.interpolation * self.inside[..., None]  # [H, W, k]
        signal = torch.relu(torch.einsum("bshw,hwk->bsk", x, weight))  # [B, S, k]
        out = signal.new_zeros(*signal.shape[:2], self.n_points)  # [B, S, n]
        return out.index_copy(2, self.visible, signal)


def _check_signal(x: torch.Tensor, channels: int, size: int, what: str) -> None:
    if x.ndim != 3 or x.shape[1:] != (channels, size):
        raise ConfigError(f"{what} must have shape (batch, {channels}, {size}), got {tuple(x.shape)}")


class IcosahedralLifting(nn.Module):
    """Lifting from a point set to the group: ``f(g) = sum_p psi(g^-1 p) Phi(p) + b``, channels mixed.

    ``psi`` ``[out, in, n]`` is a learned filter on the points (full support), drawn ``N(0, 1 / (in n))``.
    Computed as ``T[q, p] = sum_i psi[:, i, q] Phi[i, p]`` for every pair of points, then summed over
    ``p`` at ``q = g^-1 p``: ``B out n^2`` numbers, not the ``out in 60 n`` of the expanded filter.

    Input ``[B, in_channels, n]``; output ``[B, out_channels, 60]``.
    """

    def __init__(self, in_channels: int, out_channels: int, points: torch.Tensor):
        super().__init__()
        action = point_action(points)  # [60, n]
        n = action.shape[1]
        inverse = icosahedral_group().inverse
        pulled = action[inverse]  # [60, n]: index of g^-1 p
        self.in_channels, self.out_channels, self.n_points = in_channels, out_channels, n
        self.register_buffer("pair_index", (pulled * n + torch.arange(n)).flatten(), persistent=False)  # [60 n]
        self.weight = nn.Parameter(torch.randn(out_channels, in_channels, n) / math.sqrt(in_channels * n))
        self.bias = nn.Parameter(torch.zeros(out_channels))

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        _check_signal(x, self.in_channels, self.n_points, "the signal on the points")
        pairs = torch.einsum("bip,oiq->boqp", x, self.weight).flatten(2)  # [B, out, n * n]
        f = pairs[:, :, self.pair_index].unflatten(2, (GROUP_ORDER, self.n_points)).sum(-1)  # [B, out, 60]
        return f + self.bias[:, None]


class IcosahedralGroupConv(nn.Module):
    """Group convolution on the icosahedral group: ``f'(g) = sum_k psi(k^-1 g) f(k) + b``, channels mixed.

    ``psi`` ``[out, in, 60]`` is a learned filter on the group (full support), drawn
    ``N(0, 1 / (in 60))``.

    Input ``[B, in_channels, 60]``; output ``[B, out_channels, 60]``.
    """

    def __init__(self, in_channels: int, out_channels: int):
        super().__init__()
        group = icosahedral_group()
        self.in_channels, self.out_channels = in_channels, out_channels
        self.register_buffer("index", group.cayley[group.inverse], persistent=False)  # [60 (k), 60 (g)]: k^-1 g
        self.weight = nn.Parameter(torch.randn(out_channels, in_channels, GROUP_ORDER) / math.sqrt(in_channels * 60))
        self.bias = nn.Parameter(torch.zeros(out_channels))

    def forward(self, f: torch.Tensor) -> torch.Tensor:
        _check_signal(f, self.in_channels, GROUP_ORDER, "the signal on the group")
        kernel = self.weight[:, :, self.index]  # [out, in, 60 (k), 60 (g)]
        return torch.einsum("bik,oikg->bog", f, kernel) + self.bias[:, None]  # [B, out, 60]


# ---------------------------------------------------------------------------------------------- the network
class IcosahedralI2S(PoseNetwork):
    """I2S with icosahedral group convolutions and anchor regression (module docstring).

    Output ``[B, 4, 60]``: per anchor (group element) a logit, then an axis-angle residual.

    Args:
        encoder: the image encoder (:class:`~image2sphere.nn.ResNetEncoder`).
        image_size: the input size the network is built for.
        sphere_channels: channels of the signal on the points (after the projector's 1x1 convolution).
        group_channels: channels of the hidden signals on the group.
        n_group_conv: group convolutions after the lifting (0: the lifting gives the output).
        n_orbits: generic orbits of 60 points in the point set, besides the 62 axis points (0 to 3).
        taper_deg, coverage, sigma: the projection's taper start, disk coverage and Gaussian width,
            as in I2S's spatial projector.
        residual_weight: weight of the rotation loss of the label's anchor.
        rotation_loss: ``"geodesic"`` (angle in radians) or ``"frobenius"`` (squared distance).
        num_classes: > 0: the class one-hot is appended to the feature map as constant channels.
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        sphere_channels: int = 512,
        group_channels: int = 8,
        n_group_conv: int = 1,
        n_orbits: int = 2,
        taper_deg: float = 75.0,
        coverage: float = 0.9,
        sigma: float = 0.2,
        residual_weight: float = 1.0,
        rotation_loss: str = "geodesic",
        num_classes: int = 0,
    ):
        super().__init__(encoder, image_size, num_classes)
        check_int("sphere_channels", sphere_channels, 1)
        check_int("group_channels", group_channels, 1)
        check_int("n_group_conv", n_group_conv, 0)
        if rotation_loss not in ROTATION_LOSSES:
            raise ConfigError(f"rotation_loss must be one of {ROTATION_LOSSES}, got {rotation_loss!r}")
        self.residual_weight = check_number("residual_weight", residual_weight)
        self.rotation_loss = rotation_loss
        points = icosahedral_points(n_orbits)  # [n, 3]
        self.projector = PointSetProjector(
            self.feature_channels, self.feature_size, points, sphere_channels=sphere_channels,
            taper_beta=math.radians(taper_deg), coverage=coverage, sigma=sigma,
        )  # fmt: skip
        widths = [group_channels] * n_group_conv + [4]  # [lifting out, conv outs ...]; 4 = logit + residual
        self.lifting = IcosahedralLifting(sphere_channels, widths[0], points)
        layers: list[nn.Module] = []
        for a, b in zip(widths[:-1], widths[1:], strict=True):
            layers += [nn.ReLU(), IcosahedralGroupConv(a, b)]
        self.group_layers = nn.Sequential(*layers)
        last = self.group_layers[-1] if layers else self.lifting
        with torch.no_grad():  # residuals start near zero: the first predictions are the anchors
            last.weight[1:].mul_(0.1)
        self.register_buffer("anchors", icosahedral_group().matrices, persistent=False)  # [60, 3, 3] float64

    def head(self, sphere_signal: torch.Tensor) -> torch.Tensor:
        """The group part: signal on the points ``[B, S, n]`` -> output ``[B, 4, 60]``."""
        return self.group_layers(self.lifting(sphere_signal))

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` -> per anchor a logit and a residual ``[B, 4, 60]``."""
        return self.head(self.projector(self.features(images, class_index)))

    def _check_output(self, output: torch.Tensor) -> torch.Tensor:
        if not isinstance(output, torch.Tensor) or output.ndim != 3 or output.shape[1:] != (4, GROUP_ORDER):
            raise ConfigError(
                f"{type(self).__name__} output must have shape (B, 4, {GROUP_ORDER}), "
                f"got {tuple(getattr(output, 'shape', ()))}"
            )
        return output

    def corrected(self, output: torch.Tensor, anchor: torch.Tensor) -> torch.Tensor:
        """``G[k] @ exp([r_k]_x)`` ``(B, 3, 3)`` for one anchor ``k`` per image, ``anchor (B,)``."""
        output = self._check_output(output)
        residual = output[:, 1:].gather(2, anchor[:, None, None].expand(-1, 3, 1))[..., 0]  # [B, 3]
        return self.anchors.to(output.dtype)[anchor] @ rotvec_to_matrix(residual)  # [B, 3, 3]

    def nearest_anchor(self, rotation: torch.Tensor) -> torch.Tensor:
        """Index ``(B,)`` of the anchor nearest each rotation ``(B, 3, 3)`` (largest ``trace(G[k]^T R)``)."""
        trace = torch.einsum("kij,bij->bk", self.anchors.to(rotation.dtype), rotation)  # [B, 60]
        return trace.argmax(dim=1)

    def output_distribution(self, output: torch.Tensor) -> PointEstimate:
        output = self._check_output(output)
        return PointEstimate(self.corrected(output, output[:, 0].argmax(dim=1)))

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int) -> torch.Tensor:
        """Anchor cross-entropy plus ``residual_weight`` times the rotation loss of the label's anchor,
        per image ``(B,)``; ``grid_level`` is unused."""
        output = self._check_output(output)
        rotation = rotation.to(output.dtype)
        target = self.nearest_anchor(rotation.detach())  # [B]
        ce = F.cross_entropy(output[:, 0], target, reduction="none")
        corrected = self.corrected(output, target)  # [B, 3, 3]
        if self.rotation_loss == "geodesic":
            distance = geodesic_distance(corrected, rotation)
        else:
            distance = (corrected - rotation).square().sum(dim=(-1, -2))
        return ce + self.residual_weight * distance
