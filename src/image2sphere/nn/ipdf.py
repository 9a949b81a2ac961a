"""The Implicit-PDF baseline (Murphy et al. 2021, "Implicit-PDF: non-parametric representation of
probability distributions on the rotation manifold", ICML).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Images ``[B, 3, H, W]`` -> encoder map ``[B, C, h, w]`` -> global average pool ``[B, C]`` (with
  the class one-hot appended when ``num_classes > 0``): the per-image feature ``[B, F]`` that
  :meth:`IPDF.forward` returns. The MLP is evaluated lazily by the distribution
  (:class:`~image2sphere.distributions.implicit.ImplicitDistribution`).
* Score ``f(x, R)``: ``ReLU(W_x feature + W_q gamma(vec R) + b)`` -> ``depth - 1`` more ReLU layers
  of ``hidden`` units -> one scalar, the unnormalised log density. ``vec R`` is the row-major
  flattening of the ``x_camera = R @ x_object`` matrix (9 numbers); the positional encoding is
  ``gamma(v) = [sin(2^0 v), cos(2^0 v), ..., sin(2^(L-1) v), cos(2^(L-1) v)]`` (``18 L`` numbers;
  ``v`` itself when ``L = 0``), as in the authors' code (no factor ``pi``).
* Densities are w.r.t. the Haar measure of volume ``pi^2`` and are scored by the grid protocol.
* Mixed precision (:mod:`image2sphere.precision`): under autocast only the encoder runs in reduced
  precision; the features are float32, and ``forward``'s pooling, :meth:`IPDF.score`,
  :meth:`IPDF.output_distribution` and :meth:`IPDF.loss` run with autocast off
  (:class:`~image2sphere.nn.base.Float32Head`), as does the distribution's every method.
* Training loss (:meth:`IPDF.loss`): the true rotation ``R*`` among ``n`` uniformly drawn queries
  ``Q`` (one set per batch, from the torch global generator), density estimated from the softmax
  over the ``n + 1`` points, each standing for a volume ``pi^2 / (n + 1)``::

      loss = -log( exp f(R*) / (exp f(R*) + sum_q exp f(q)) * (n + 1) / pi^2 )

  (a uniform ``f`` gives ``log(pi^2)``, the negative log density of the uniform distribution).
"""

from __future__ import annotations

import math

import torch
from torch import nn

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY
from image2sphere.distributions.implicit import ImplicitDistribution
from image2sphere.nn.base import Float32Head
from image2sphere.rotation_sets import check_labels
from image2sphere.so3.grid import so3_grid_size, so3_healpix_grid
from image2sphere.so3.rotations import random_rotations

__all__ = ["IPDF", "QUERY_SAMPLING", "positional_encoding"]

QUERY_SAMPLING = ("random", "grid")


def positional_encoding(x: torch.Tensor, num_fourier: int) -> torch.Tensor:
    """``[..., D]`` -> ``[..., 2 * num_fourier * D]``: ``[sin(2^k x), cos(2^k x)]`` for ``k < num_fourier``,
    frequency-major (``x`` itself when ``num_fourier == 0``)."""
    if num_fourier == 0:
        return x
    freqs = 2.0 ** torch.arange(num_fourier, dtype=x.dtype, device=x.device)  # [L]
    angles = x[..., None, :] * freqs[:, None]  # [..., L, D]
    return torch.cat([angles.sin(), angles.cos()], dim=-1).flatten(-2)  # [..., L * 2D]


class IPDF(Float32Head):
    """Implicit-PDF: an MLP scores (image feature, rotation) pairs; the softmax over SO(3) is the pose
    distribution.

    Args:
        encoder: a module with ``out_channels`` and ``forward(images) -> [B, C, h, w]`` (e.g.
            :class:`image2sphere.nn.ResNetEncoder`; the paper uses an ImageNet ResNet-101).
        image_size: input image size (unused: the features are globally pooled; kept so every pose
            network is configured alike).
        hidden: units of each MLP layer.
        depth: number of hidden layers (the first adds the projected feature and the projected
            rotation encoding).
        num_fourier: positional-encoding frequencies of the flattened rotation (0: the raw 9 numbers).
        n_queries: uniform query rotations per training step.
        num_classes: if > 0, the class one-hot is appended to the pooled feature.
        query_sampling: ``"random"`` (``n_queries`` Haar-random rotations) or ``"grid"`` (the HEALPix
            grid whose size is closest to ``n_queries`` in log scale, under one random rotation per
            step; level 2, 4608 points, for 4096).

    The authors' settings (github.com/google-research/google-research, ``implicit_pdf/README.md``
    and ``train.py``): SYMSOL I: ``hidden=256, depth=4, num_fourier=3, n_queries=4096``, random
    queries, batch 128, Adam lr 1e-4, 100k steps, evaluated on ~2M grid points. PASCAL3D+:
    ``hidden=256, depth=2``, ``n_queries=4096`` on the grid, batch 64, lr 1e-5, 150k steps.
    Layers are initialised as Keras' ``Dense`` (Glorot-uniform weights, zero biases).
    """

    FLOAT32_METHODS = (*Float32Head.FLOAT32_METHODS, "score")

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        hidden: int = 256,  # paper: 256
        depth: int = 4,  # paper: 4 (SYMSOL), 2 (PASCAL3D+)
        num_fourier: int = 3,  # paper: 3 (SYMSOL)
        n_queries: int = 4096,  # paper: 2**12
        num_classes: int = 0,
        query_sampling: str = "random",  # paper: "random" (SYMSOL), "grid" (PASCAL3D+)
    ):
        super().__init__()
        for name, value, low in (("hidden", hidden, 1), ("depth", depth, 1), ("num_fourier", num_fourier, 0),
                                 ("n_queries", n_queries, 1), ("num_classes", num_classes, 0)):  # fmt: skip
            check_int(name, value, low)
        if query_sampling not in QUERY_SAMPLING:
            raise ConfigError(f"query_sampling must be one of {QUERY_SAMPLING}, got {query_sampling!r}")
        self.encoder = encoder
        self.image_size = image_size
        self.hidden = hidden
        self.depth = depth
        self.num_fourier = num_fourier
        self.n_queries = n_queries
        self.num_classes = num_classes
        self.query_sampling = query_sampling
        self.feature_dim = int(encoder.out_channels) + num_classes
        self.query_dim = 9 * (2 * num_fourier if num_fourier else 1)
        self.feature_proj = nn.Linear(self.feature_dim, hidden)
        self.query_proj = nn.Linear(self.query_dim, hidden, bias=False)  # one bias for the summed layer
        layers: list[nn.Module] = []
        for _ in range(depth - 1):
            layers += [nn.Linear(hidden, hidden), nn.ReLU()]
        self.layers = nn.Sequential(*layers)
        self.head = nn.Linear(hidden, 1)
        for module in (self.feature_proj, self.query_proj, *self.layers, self.head):  # not the encoder's
            if isinstance(module, nn.Linear):
                nn.init.xavier_uniform_(module.weight)
                if module.bias is not None:
                    nn.init.zeros_(module.bias)

    # ------------------------------------------------------------------ features
    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` (and class indices ``[B]``) -> per-image features ``[B, F]``."""
        x = self.encode(images)  # float32 under autocast
        if x.ndim != 4 or x.shape[1] != self.feature_dim - self.num_classes:
            raise ConfigError(
                f"the encoder must return (B, {self.feature_dim - self.num_classes}, h, w), got {tuple(x.shape)}"
            )
        x = x.mean(dim=(-1, -2))  # [B, C]
        if self.num_classes == 0:
            return x
        if class_index is None:
            raise ConfigError(f"this model was built with num_classes={self.num_classes}: pass class_index")
        class_index = torch.as_tensor(class_index, device=x.device)
        if class_index.shape != (len(x),) or ((class_index < 0) | (class_index >= self.num_classes)).any():
            raise ConfigError(
                f"class_index must be integers in [0, {self.num_classes}) of shape ({len(x)},), "
                f"got shape {tuple(class_index.shape)}"
            )
        onehot = nn.functional.one_hot(class_index.long(), self.num_classes).to(x.dtype)  # [B, nc]
        return torch.cat([x, onehot], dim=1)  # [B, C + nc]

    # ------------------------------------------------------------------ the implicit function
    def _check_features(self, features: torch.Tensor) -> None:
        if not isinstance(features, torch.Tensor) or features.ndim != 2 or features.shape[1] != self.feature_dim:
            shape = tuple(features.shape) if isinstance(features, torch.Tensor) else type(features).__name__
            raise ConfigError(f"features must have shape (B, {self.feature_dim}), got {shape}")

    def score(self, features: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
        """Unnormalised log density ``(B, K)`` of features ``(B, F)`` at rotations ``(K, 3, 3)`` (shared:
        the rotation embedding is computed once and broadcast) or ``(B, K, 3, 3)``."""
        self._check_features(features)
        if rotations.ndim not in (3, 4) or rotations.shape[-2:] != (3, 3):
            raise ConfigError(f"rotations must have shape (K, 3, 3) or (B, K, 3, 3), got {tuple(rotations.shape)}")
        if rotations.ndim == 4 and rotations.shape[0] != features.shape[0]:
            raise ConfigError(
                f"rotations of shape (B, K, 3, 3) must have B = {features.shape[0]}, got {tuple(rotations.shape)}"
            )
        rotations = rotations.to(dtype=features.dtype, device=features.device)
        query = positional_encoding(rotations.flatten(-2), self.num_fourier)  # [(B,) K, Q]
        h = self.query_proj(query)  # [(B,) K, W]
        h = torch.relu(self.feature_proj(features)[:, None, :] + h)  # [B, 1, W] + [(B,) K, W] -> [B, K, W]
        h = self.layers(h)  # [B, K, W]
        return self.head(h).squeeze(-1)  # [B, K]

    def output_distribution(self, features: torch.Tensor) -> ImplicitDistribution:
        """The pose distribution of each image from its features ``(B, F)`` (the network's output)."""
        self._check_features(features)
        return ImplicitDistribution(features, self.score, width=self.hidden)

    def distribution(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> ImplicitDistribution:
        """The predicted distribution over rotations for each image."""
        return self.output_distribution(self(images, class_index))

    # ------------------------------------------------------------------ training
    def train_queries(self, dtype: torch.dtype = torch.float32, device=None) -> torch.Tensor:
        """The query rotations of one training step ``(n, 3, 3)``, drawn with the torch global generator."""
        if self.query_sampling == "random":
            return random_rotations(self.n_queries, dtype=dtype, device=device)
        sizes = [math.prod(so3_grid_size(level)) for level in range(6)]
        level = min(range(6), key=lambda i: abs(math.log(sizes[i]) - math.log(self.n_queries)))
        grid = so3_healpix_grid(level, dtype=dtype).to(device)  # [n, 3, 3]
        offset = random_rotations(1, dtype=dtype, device=device)[0]  # [3, 3]
        return torch.einsum("ij,njk->nik", offset, grid)  # [n, 3, 3]

    def loss(self, features: torch.Tensor, rotation: torch.Tensor, grid_level: int | None = None) -> torch.Tensor:
        """Negative log density estimate ``(B,)`` of the true ``rotation (B, 3, 3)`` (module docstring).

        ``grid_level`` is accepted for the interface every pose network shares and is not used: the
        normalisation comes from :attr:`n_queries` query rotations (:meth:`train_queries`)."""
        check_labels(rotation, len(features))  # a head, not a PoseNetwork: its own check
        distribution = self.output_distribution(features)
        queries = self.train_queries(features.dtype, features.device)  # [n, 3, 3]
        true = distribution.unnormalized_log_density(rotation[:, None])  # [B, 1]
        others = distribution.unnormalized_log_density(queries)  # [B, n]
        log_norm = torch.logsumexp(torch.cat([true, others], dim=1), dim=1)  # [B]
        n_points = 1 + len(queries)
        return -(true[:, 0] - log_norm + math.log(n_points) + LOG_UNIFORM_DENSITY)
