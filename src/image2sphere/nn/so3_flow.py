"""Normalizing flows on SO(3) conditioned on an image (Liu et al., "Delving into Discrete Normalizing
Flows on SO(3) Manifold for Probabilistic Rotation Modeling", CVPR 2023).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``; columns ``c_0, c_1, c_2`` with
  ``c_k = c_i x c_j`` for every cyclic ``(i, j, k)``.
* Densities are w.r.t. the Haar measure of volume ``pi^2``. The base distribution is the uniform one,
  log density ``-log(pi^2)``.
* A flow is a chain of bijections ``T = T_K o ... o T_1`` of SO(3), each with parameters computed from
  the image's condition vector ``z`` ``(B, F)``. A sample is ``R = T(R_0)`` with ``R_0`` uniform; the
  density is exact (change of variables), evaluated backwards from ``R_K = R``::

      R_{k-1} = T_k^{-1}(R_k),   log p(R) = -log(pi^2) + sum_k log |det J_{T_k^{-1}}(R_k)|

  every determinant taken w.r.t. the Haar measure (so the uniform density is a fixed point of the
  bookkeeping, and ``exp(log p)`` integrates to 1 over SO(3) exactly).
* **Möbius coupling** about column ``i`` (:class:`MobiusCoupling`): ``c_i`` is kept; ``c_j`` lies on the
  unit circle orthogonal to ``c_i`` and is moved by the disk automorphism (a Möbius transformation of
  the circle, written in the circle's plane)::

      h_w(x) = (1 - |w|^2) / |x - w|^2 * (x - w) - w,     w in the plane, |w| < 1

  then turned by an angle ``phi`` about ``c_i``; ``c_k = c_i x c_j``. ``w`` and ``phi`` come from an
  MLP of ``(c_i, z)``. The Haar measure is the area measure of ``c_i`` on S^2 times the angle of
  ``c_j`` on its circle, and the map keeps ``c_i``, so its Jacobian is the circle map's derivative
  ``|h_w'(x)| = (1 - |w|^2) / |x - w|^2``. The inverse is exact: turn back by ``-phi``, then
  ``h_{-w}``.
* **Quaternion affine** (:class:`QuaternionAffine`): the unit quaternion of the rotation is mapped
  ``q -> W q / |W q|`` (well defined on rotations: ``-q`` maps to minus the image), ``W = exp(A)`` with
  ``A`` ``4 x 4`` from ``z``, so ``W`` is always invertible, ``det W = exp(tr A)`` and
  ``W^{-1} = exp(-A)``. Its Jacobian on S^3, hence w.r.t. the Haar measure (S^3 covers SO(3) twice,
  evenly), is ``det W / |W q|^4``.
* ``start="identity"`` (the default): every layer starts as the identity (its last linear layer at
  zero), so the first prediction is the uniform distribution, as I2S's. ``start="random"``: PyTorch's
  default initialisation of those layers too, as in the authors' code, so the flow starts as a random
  non-uniform distribution (docs/methods.md, "Successors at small scale", says why this matters for
  shapes whose symmetry group keeps no axis).

The layers are exactly invertible in closed form; the paper's variant that averages several Möbius
transformations in angle space needs a numerical inverse and is not used here (a chain of single
transformations is as expressive in the limit and keeps sampling and density exact both ways).
"""

from __future__ import annotations

import threading

import torch
from torch import nn

from image2sphere.checks import check_int
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY
from image2sphere.distributions.flow import FlowDistribution
from image2sphere.nn.base import PoseNetwork, check_rotation_set
from image2sphere.so3.rotations import matrix_to_quaternion, quaternion_to_matrix, random_rotations

__all__ = ["MobiusCoupling", "QuaternionAffine", "RotationFlow", "SO3Flow", "mobius_circle"]

#: ``|w| <= W_MAX``: the densest a single Möbius layer can make a circle is ``(1 + W_MAX) / (1 - W_MAX)``
W_MAX = 0.99


def _check_start(start: str, name: str = "start") -> str:
    if start not in ("identity", "random"):
        raise ValueError(f"{name} must be 'identity' or 'random', got {start!r}")
    return start


def mobius_circle(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The disk automorphism ``h_w`` on unit vectors ``x (..., 3)`` of a plane that holds ``w (..., 3)``
    (``|w| < 1``): ``(h_w(x) (..., 3), log |h_w'(x)| (...))``. Its inverse is ``h_{-w}``."""
    diff = x - w  # [..., 3]
    sq = (diff * diff).sum(-1)  # [...]
    scale = (1 - (w * w).sum(-1)) / sq  # [...]
    return scale[..., None] * diff - w, scale.log()


def _turn(x: torch.Tensor, axis: torch.Tensor, phi: torch.Tensor) -> torch.Tensor:
    """``x (..., 3)`` orthogonal to the unit ``axis (..., 3)`` turned by ``phi (...)`` about it."""
    return phi.cos()[..., None] * x + phi.sin()[..., None] * torch.linalg.cross(axis, x, dim=-1)


class MobiusCoupling(nn.Module):
    """One Möbius coupling layer about column ``column`` (module docstring).

    Args:
        column: the column ``i`` that is kept (0, 1 or 2); ``c_{i+1}`` is transformed.
        condition_dim: size of the condition vector ``z``.
        hidden: units of the conditioner's hidden layers.
        depth: hidden layers of the conditioner (>= 1).
        start: ``"identity"`` (last layer at zero) or ``"random"`` (PyTorch's default initialisation).
    """

    def __init__(self, column: int, condition_dim: int, hidden: int = 64, depth: int = 2, start: str = "identity"):
        super().__init__()
        if column not in (0, 1, 2):
            raise ValueError(f"column must be 0, 1 or 2, got {column!r}")
        check_int("hidden", hidden, 1)
        check_int("depth", depth, 1)
        self.i, self.j, self.k = column, (column + 1) % 3, (column + 2) % 3
        self.hidden = hidden
        self.from_condition = nn.Linear(condition_dim, hidden)
        self.from_column = nn.Linear(3, hidden, bias=False)  # one bias for the summed first layer
        layers: list[nn.Module] = []
        for _ in range(depth - 1):
            layers += [nn.Linear(hidden, hidden), nn.ReLU()]
        self.layers = nn.Sequential(*layers)
        self.out = nn.Linear(hidden, 4)  # w (3, projected onto the circle's plane), phi
        if _check_start(start) == "identity":
            nn.init.zeros_(self.out.weight)
            nn.init.zeros_(self.out.bias)

    def parameters_at(self, z: torch.Tensor, axis: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``w (B, K, 3)`` (in the plane orthogonal to ``axis``, ``|w| < W_MAX``) and ``phi (B, K)`` for
        conditions ``z (B, F)`` and kept columns ``axis (B, K, 3)``.

        The hidden activations ``(B, K, H)`` are the costly part of a grid sweep (K rotations per image): the
        first layer is one batched product with the image's condition term as its bias, and each activation
        is rectified in place. Without autograd they are written into buffers kept between calls
        (:meth:`_scratch`): a sweep calls this with the same shapes hundreds of times, and fresh
        multi-megabyte outputs cost about as much as the products that fill them."""
        B, K = axis.shape[:2]
        condition = self.from_condition(z)  # [B, H]
        weight = self.from_column.weight.T.expand(B, 3, self.hidden)  # [B, 3, H]
        if torch.is_grad_enabled():
            h = torch.baddbmm(condition[:, None, :], axis, weight).relu_()  # [B, K, H]
            for layer in self.layers:  # Linear, ReLU, ... (ReLU in place: its input is not needed again)
                h = h.relu_() if isinstance(layer, nn.ReLU) else layer(h)
            out = self.out(h)  # [B, K, 4]
        else:
            h = torch.baddbmm(condition[:, None, :], axis, weight, out=self._scratch("in", B, K, axis)).relu_()
            h = h.view(B * K, -1)  # [B K, H]
            for index, layer in enumerate(self.layers):
                if isinstance(layer, nn.ReLU):
                    h.relu_()
                else:
                    h = torch.addmm(
                        layer.bias, h, layer.weight.T, out=self._scratch(f"hidden{index}", B, K, axis).view(B * K, -1)
                    )
            out = torch.addmm(self.out.bias, h, self.out.weight.T).view(B, K, 4)  # [B, K, 4]: new, returned
        v = out[..., :3]
        v = v - (v * axis).sum(-1, keepdim=True) * axis  # in the plane of the circle
        norm = torch.linalg.vector_norm(v, dim=-1, keepdim=True)
        w = v * (W_MAX / (1 + norm))  # |w| = W_MAX |v| / (1 + |v|) < W_MAX
        return w, out[..., 3]

    def _scratch(self, name: str, B: int, K: int, like: torch.Tensor) -> torch.Tensor:
        """A ``(B, K, hidden)`` buffer of ``like``'s dtype and device, kept for the next call with the same
        shape in the same thread (per thread: two threads evaluating one model at once, as a server's
        request handlers may, never share one; the buffers of one shape at a time per thread: a sweep uses
        one chunk size, its last chunk another). A buffer made under ``torch.inference_mode`` (Lightning's test
        loop) cannot be written outside it (``torch.no_grad``, a prediction afterwards), so the mode is part of
        the key."""
        key = (B, K, like.dtype, like.device, torch.is_inference_mode_enabled())
        per_thread = self.__dict__.setdefault("_scratch_by_thread", {})
        shape, buffers = per_thread.get(threading.get_ident(), (None, None))
        if shape != key:
            buffers = {}
            per_thread[threading.get_ident()] = (key, buffers)
        if name not in buffers:
            buffers[name] = torch.empty(B, K, self.hidden, dtype=like.dtype, device=like.device)
        return buffers[name]

    def map_columns(
        self, columns: tuple[torch.Tensor, torch.Tensor, torch.Tensor], z: torch.Tensor, inverse: bool = False
    ) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
        """The layer (or its inverse) on a rotation given by its columns ``(c_0, c_1, c_2)``, each
        ``(B, K, 3)``: the new columns and ``log |det J| (B, K)``. Column ``i`` is passed on as it is."""
        axis, x = columns[self.i], columns[self.j]  # [B, K, 3] each
        w, phi = self.parameters_at(z, axis)
        if inverse:
            y, log_det = mobius_circle(_turn(x, axis, -phi), -w)  # h_{-w} after turning back
        else:
            y, log_det = mobius_circle(x, w)
            y = _turn(y, axis, phi)
        y = nn.functional.normalize(y - (y * axis).sum(-1, keepdim=True) * axis, dim=-1)  # rounding only
        out = [axis, axis, axis]
        out[self.j], out[self.k] = y, torch.linalg.cross(axis, y, dim=-1)
        return (out[0], out[1], out[2]), log_det

    def _map(self, R: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        columns, log_det = self.map_columns(tuple(R.unbind(-1)), z, inverse)
        return torch.stack(columns, dim=-1), log_det  # [B, K, 3, 3], [B, K]

    def forward(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R)`` and ``log |det J_T(R)|`` for rotations ``R (B, K, 3, 3)`` and conditions ``z (B, F)``."""
        return self._map(R, z, inverse=False)

    def inverse(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T^{-1}(R)`` and ``log |det J_{T^{-1}}(R)|``, exactly."""
        return self._map(R, z, inverse=True)


class QuaternionAffine(nn.Module):
    """``q -> W q / |W q|`` with ``W = exp(A(z))`` (module docstring).

    Args:
        condition_dim: size of the condition vector ``z``; ``A`` is a linear function of it (zero at
            the start with ``start="identity"``: the identity).
        start: ``"identity"`` or ``"random"`` (PyTorch's default initialisation of the linear map).
    """

    def __init__(self, condition_dim: int, start: str = "identity"):
        super().__init__()
        self.to_matrix = nn.Linear(condition_dim, 16)
        if _check_start(start) == "identity":
            nn.init.zeros_(self.to_matrix.weight)
            nn.init.zeros_(self.to_matrix.bias)

    def _map(self, R: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        A = self.to_matrix(z).reshape(-1, 4, 4)  # [B, 4, 4]
        if inverse:
            A = -A
        W = torch.linalg.matrix_exp(A)  # [B, 4, 4]
        q = matrix_to_quaternion(R, "wxyz")  # [B, K, 4]
        Wq = torch.bmm(q, W.transpose(1, 2))  # [B, K, 4]
        norm = torch.linalg.vector_norm(Wq, dim=-1)  # [B, K]
        log_det = A.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None] - 4 * norm.log()  # log det W - 4 log |W q|
        return quaternion_to_matrix(Wq, "wxyz"), log_det

    def map_columns(
        self, columns: tuple[torch.Tensor, torch.Tensor, torch.Tensor], z: torch.Tensor, inverse: bool = False
    ) -> tuple[tuple[torch.Tensor, torch.Tensor, torch.Tensor], torch.Tensor]:
        """As :meth:`MobiusCoupling.map_columns`: the layer on a rotation's columns, each ``(B, K, 3)``."""
        R, log_det = self._map(torch.stack(columns, dim=-1), z, inverse)
        return tuple(R.unbind(-1)), log_det

    def forward(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R)`` and ``log |det J_T(R)|`` for ``R (B, K, 3, 3)`` and ``z (B, F)``."""
        return self._map(R, z, inverse=False)

    def inverse(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T^{-1}(R)`` and ``log |det J_{T^{-1}}(R)|``, exactly (``W^{-1} = exp(-A)``)."""
        return self._map(R, z, inverse=True)


class SO3Flow(nn.Module):
    """A conditional flow on SO(3): ``blocks`` times (Möbius couplings about columns 0, 1, 2, then a
    quaternion affine layer), from the uniform distribution (module docstring).

    Args:
        condition_dim: size of the condition vector ``z`` ``(B, F)``.
        blocks: number of (3 couplings + 1 affine) blocks.
        hidden, depth: each coupling's conditioner MLP.
        start: ``"identity"`` (the uniform distribution at the start) or ``"random"`` (module docstring).
    """

    def __init__(self, condition_dim: int, blocks: int = 4, hidden: int = 64, depth: int = 2, start: str = "identity"):
        super().__init__()
        check_int("condition_dim", condition_dim, 1)
        check_int("blocks", blocks, 1)
        layers: list[nn.Module] = []
        for _ in range(blocks):
            layers += [MobiusCoupling(c, condition_dim, hidden, depth, start) for c in range(3)]
            layers.append(QuaternionAffine(condition_dim, start))
        self.layers = nn.ModuleList(layers)
        self.condition_dim = condition_dim
        self.hidden = hidden

    @staticmethod
    def _batched(R: torch.Tensor, z: torch.Tensor) -> torch.Tensor:
        if R.ndim == 3:  # shared rotations
            return R.expand(len(z), *R.shape)
        if R.ndim != 4 or R.shape[0] != len(z) or R.shape[-2:] != (3, 3):
            raise ValueError(f"rotations must have shape (K, 3, 3) or ({len(z)}, K, 3, 3), got {tuple(R.shape)}")
        return R

    def log_prob(self, z: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        """The exact log density ``(B, K)`` (Haar measure of volume ``pi^2``) at rotations ``R`` ``(K, 3, 3)``
        (shared) or ``(B, K, 3, 3)`` for conditions ``z (B, F)``."""
        R = self._batched(R.to(z), z)
        columns = tuple(R.unbind(-1))  # each [B, K, 3]: the couplings read and write columns
        total = torch.zeros(R.shape[:2], dtype=z.dtype, device=z.device)  # [B, K]
        for layer in reversed(self.layers):
            columns, log_det = layer.map_columns(columns, z, inverse=True)
            total = total + log_det
        return total + LOG_UNIFORM_DENSITY

    def transform(self, z: torch.Tensor, R0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R0)`` ``(B, K, 3, 3)`` and ``log |det J_T(R0)|`` ``(B, K)`` (the forward direction)."""
        R = self._batched(R0.to(z), z)
        columns = tuple(R.unbind(-1))  # each [B, K, 3]
        total = torch.zeros(R.shape[:2], dtype=z.dtype, device=z.device)
        for layer in self.layers:
            columns, log_det = layer.map_columns(columns, z)
            total = total + log_det
        return torch.stack(columns, dim=-1), total

    def sample(self, z: torch.Tensor, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)`` per condition: uniform rotations pushed through the flow."""
        check_int("n", n, 1)
        R0 = random_rotations(len(z) * n, generator=generator, dtype=z.dtype, device="cpu").to(z.device)
        return self.transform(z, R0.reshape(len(z), n, 3, 3))[0]


class RotationFlow(PoseNetwork):
    """Image-conditioned normalizing flow on SO(3) (Liu et al., CVPR 2023): the pooled encoder features
    (with the class one-hot when ``num_classes > 0``) are the condition of an :class:`SO3Flow`; the
    output distribution (:class:`~image2sphere.distributions.flow.FlowDistribution`) has an exact density,
    exact samples and a normaliser of exactly 1; the loss is the negative log likelihood of the label.

    Args:
        encoder, image_size, num_classes, input_scaling: as every pose network (:class:`PoseNetwork`).
        condition_dim: the pooled features are mapped to this many numbers (linear + ReLU) before
            they condition every layer; ``0``: the pooled features themselves.
        blocks, hidden, depth, start: the flow (:class:`SO3Flow`).
    """

    def __init__(
        self,
        encoder: nn.Module,
        image_size: int | tuple[int, int] = 224,
        condition_dim: int = 256,
        blocks: int = 4,
        hidden: int = 64,
        depth: int = 2,
        start: str = "identity",
        num_classes: int = 0,
        input_scaling: str = "imagenet",
    ):
        _check_start(start, "model.net.start")
        super().__init__(encoder, image_size, num_classes, input_scaling)
        check_int("condition_dim", condition_dim, 0)
        if condition_dim:
            self.condition = nn.Sequential(nn.Linear(self.feature_channels, condition_dim), nn.ReLU())
        else:
            self.condition, condition_dim = nn.Identity(), self.feature_channels
        self.flow = SO3Flow(condition_dim, blocks, hidden, depth, start)

    def forward(self, images: torch.Tensor, class_index: torch.Tensor | None = None) -> torch.Tensor:
        """Images ``[B, 3, H, W]`` (and class indices ``[B]``) -> conditions ``[B, F]``."""
        return self.condition(self.pooled_features(images, class_index))  # [B, C] -> [B, F]

    def output_distribution(self, output: torch.Tensor) -> FlowDistribution:
        """The flow's distribution for each image's condition ``output (B, F)``."""
        return FlowDistribution(output, self.flow.log_prob, self.flow.sample, width=self.flow.hidden)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int | None = None) -> torch.Tensor:
        """The negative log likelihood ``(B,)`` of ``rotation (B, 3, 3)``, exact (``grid_level`` unused)."""
        if not isinstance(rotation, torch.Tensor) or rotation.shape != (len(output), 3, 3):
            shape = tuple(rotation.shape) if isinstance(rotation, torch.Tensor) else type(rotation).__name__
            raise ValueError(f"rotation must have shape ({len(output)}, 3, 3), got {shape}")
        return -self.flow.log_prob(output, rotation[:, None])[:, 0]

    def set_loss(
        self, output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor, grid_level: int
    ) -> torch.Tensor:
        """The negative log likelihood averaged over each image's equivalent ``rotations (B, M, 3, 3)``
        where ``mask (B, M)``: one batched pass of the flow for every rotation of the set."""
        check_rotation_set(output, rotations, mask)
        real = mask.to(output)
        from image2sphere.metrics import fill_padding  # here: metrics imports the nn package's users

        log_p = self.flow.log_prob(output, fill_padding(rotations, mask).to(output))  # [B, M]
        return -(log_p * real).sum(1) / real.sum(1)
