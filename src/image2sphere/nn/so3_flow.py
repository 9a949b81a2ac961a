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
  evenly), is ``det W / |W q|^4``. A multiple of the identity in ``A`` only scales ``W``, which the map
  divides out, so ``A`` is taken traceless (its trace removed): the same family of maps, ``det W = 1``,
  and no ``exp(tr A)`` to overflow.
* ``start="identity"`` (the default): every layer starts as the identity (its last linear layer at
  zero), so the first prediction is the uniform distribution, as I2S's. ``start="random"``: PyTorch's
  default initialisation of those layers too, as in the authors' code, so the flow starts as a random
  non-uniform distribution (docs/methods.md, "Successors at small scale", says why this matters for
  shapes whose symmetry group keeps no axis).

The layers are exactly invertible in closed form; the paper's variant that averages several Möbius
transformations in angle space needs a numerical inverse and is not used here (a chain of single
transformations is as expressive in the limit and keeps sampling and density exact both ways).

How the flow is evaluated: a unit quaternion per rotation
---------------------------------------------------------
The grid protocol runs the flow at every point of an SO(3) grid (294,912 per image at level 4), so the
layers are computed on the rotations' unit quaternions ``q = (w, x, y, z)`` (Hamilton product,
``R(p q) = R(p) R(q)``), held as ``(4, B, K)``: each component is a row of the ``N = B K`` rotations of a
call, so every step is one vectorised operation over all of them, each conditioner layer is one matrix
product with ``N`` columns, and nothing is converted between matrices and quaternions between layers. The
mathematics above is unchanged; only its arithmetic is:

* A coupling about column ``i`` keeps ``c_i`` and moves ``c_j`` on its circle, ``c_k`` following: the new
  rotation is the old one turned about ``c_i`` by some angle ``a``, ``R' = R Rot(e_i, a)``, i.e.
  ``q' = q (cos(a/2), sin(a/2) e_i)``. In the circle's plane with coordinates along ``(c_j, c_k)``, ``c_j``
  is the complex number 1 and ``w = w_j + i w_k``. On the unit circle the disk automorphism is
  ``h_w(x) = conj(x) (x - w)^2 / |x - w|^2``, so the half angle needs no arc tangent: forwards
  ``exp(i a/2) = exp(i phi/2) (1 - w) / |1 - w|`` and ``log |det J| = log(1 - |w|^2) - log |1 - w|^2``;
  backwards (turn by ``-phi``, then ``h_{-w}``) ``exp(i a/2) = u / |u|`` with
  ``u = exp(-i phi/2) + w exp(i phi/2)`` and ``log |det J| = log(1 - |w|^2) - log |u|^2``.
* The columns are quadratic in ``q``: with the 16 products ``q_a q_b`` (one outer product), the nine
  entries of ``R`` are one small matrix product (:data:`_ROTATION_FORM`), which gives the conditioner's
  input ``c_i`` and the coordinates ``v . c_j``, ``v . c_k`` of its output ``v`` in the circle's plane.
* Without autograd (a grid sweep) the products, activations and each layer's quaternions are written into
  buffers kept between calls and shared by the layers of one flow (:class:`_Buffers`), and the elementwise
  steps overwrite their temporaries. The conditioners run on pieces of the rotations that stay in a core's
  cache from one layer to the next; the first layer adds each image's condition term through a one-hot code
  of the images, and each later bias is the last column of its layer's matrix, the activations having a row
  of ones below them: each layer is one matrix product and one rectification.
"""

from __future__ import annotations

import threading

import torch
from torch import nn

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY
from image2sphere.distributions.flow import FlowDistribution
from image2sphere.nn.base import PoseNetwork
from image2sphere.rotation_sets import check_rotation_set, fill_padding
from image2sphere.so3.rotations import matrix_to_quaternion, quaternion_to_matrix, random_rotations

__all__ = ["MobiusCoupling", "QuaternionAffine", "RotationFlow", "SO3Flow", "mobius_circle"]

#: activations per piece of a conditioner's layers and per thread on a CPU (512 KiB of float32, in a core's
#: cache from one layer to the next). Measured when it was chosen, on one thread of this project's CPU: a
#: coupling of 16 x 1024 rotations in 1.72 ms, against 1.81 ms at 1 << 18 and 1.89 ms at 1 << 19
PIECE_ELEMENTS = 1 << 17
#: the width a grid sweep on a CPU divides its activation budget by (rotations per call: 4096 of 16 images,
#: :class:`~image2sphere.distributions.implicit.ImplicitDistribution`): the conditioners' activations are in
#: pieces anyway, and larger calls spread the layers' fixed costs and give each elementwise step enough
#: numbers for two threads. Measured when it was chosen, a level-3 sweep of 16 images on two idle cores of a
#: Xeon: 0.72 s, against 0.77 s at 32 and 0.90 s at the hidden width, 64. Elsewhere: the hidden width.
CPU_CALL_WIDTH = 16
#: ``|w| <= W_MAX``: the densest a single Möbius layer can make a circle is ``(1 + W_MAX) / (1 - W_MAX)``
W_MAX = 0.99


def _check_start(start: str, name: str = "start") -> str:
    if start not in ("identity", "random"):
        raise ConfigError(f"{name} must be 'identity' or 'random', got {start!r}")
    return start


def mobius_circle(x: torch.Tensor, w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """The disk automorphism ``h_w`` on unit vectors ``x (..., 3)`` of a plane that holds ``w (..., 3)``
    (``|w| < 1``): ``(h_w(x) (..., 3), log |h_w'(x)| (...))``. Its inverse is ``h_{-w}``. (The layers use
    its half-angle form, module docstring; this is the map as written in the paper.)"""
    diff = x - w  # [..., 3]
    sq = (diff * diff).sum(-1)  # [...]
    scale = (1 - (w * w).sum(-1)) / sq  # [...]
    return scale[..., None] * diff - w, scale.log()


def _levi_civita(a: int, b: int, c: int) -> int:
    return (a - b) * (b - c) * (c - a) // 2  # +1, -1 or 0 for indices in 0..2


def _rotation_form() -> torch.Tensor:
    """``F (3, 3, 16)`` float64 with ``R(q)[m, n] = sum_p F[m, n, p] (q q^T)[p]`` for unit ``q`` (wxyz,
    ``q q^T`` flattened row-major): ``R = (w^2 - |v|^2) I + 2 v v^T + 2 w [v]_x``, each term split evenly
    over the two symmetric products."""
    F = torch.zeros(3, 3, 4, 4, dtype=torch.float64)
    for m in range(3):
        F[m, m, 0, 0] += 1
        for s in range(3):
            F[m, m, 1 + s, 1 + s] -= 1
        for n in range(3):
            F[m, n, 1 + m, 1 + n] += 1
            F[m, n, 1 + n, 1 + m] += 1
            for ell in range(3):  # ([v]_x)[m, n] = eps(m, l, n) v_l
                F[m, n, 0, 1 + ell] += _levi_civita(m, ell, n)
                F[m, n, 1 + ell, 0] += _levi_civita(m, ell, n)
    return F.reshape(3, 3, 16)


#: :func:`_rotation_form`: the rotation matrix as a linear map of the products ``q_a q_b``
_ROTATION_FORM = _rotation_form()


def _times_axis(i: int) -> torch.Tensor:
    """``E (4, 4)`` float64 with ``E q = q (0, e_i)`` (Hamilton product with the unit pure quaternion of axis
    ``i``): scalar ``-v_i``, vector ``w e_i + v x e_i``."""
    E = torch.zeros(4, 4, dtype=torch.float64)
    E[0, 1 + i] = -1
    E[1 + i, 0] = 1
    for m in range(3):
        for ell in range(3):
            E[1 + m, 1 + ell] = _levi_civita(m, ell, i)
    return E


def _quaternions(R: torch.Tensor) -> torch.Tensor:
    """Rotations ``(K, 3, 3)`` or ``(B, K, 3, 3)`` -> unit quaternions ``(4, K)`` or ``(4, B, K)`` (wxyz, the
    components first: each a row of contiguous numbers)."""
    q = matrix_to_quaternion(R, "wxyz")  # [(B,) K, 4]
    return q.permute(-1, *range(q.ndim - 1)).contiguous()


def _rotations(q: torch.Tensor) -> torch.Tensor:
    """Quaternions ``(4, B, K)`` -> rotations ``(B, K, 3, 3)``."""
    return quaternion_to_matrix(q.permute(1, 2, 0), "wxyz")


class _Buffers:
    """Work buffers for ``B x K`` rotations of one dtype, device and autograd mode, shared by the layers of a
    flow (the layers run one after another, each done with them before the next starts).

    The conditioners run on pieces of the ``N = B K`` rotations (image-major columns): either whole images
    (up to ``PIECE_ELEMENTS * threads / hidden`` columns on a CPU, all of them elsewhere) or, where one image
    has more rotations than that, a part of one image. The columns buffer has, below the rotation's nine
    entries, one row per image of a piece, 1 in that image's columns (a one-hot code: the first layer's
    product adds each image's condition term by it). :attr:`pieces` holds each piece's views of the buffers,
    made once (slicing costs a few microseconds a view, and a sweep slices the same views thousands of
    times). The layers write their quaternions into two buffers in turn (:meth:`output_for`), the affine
    layers' products into a third."""

    def __init__(self, B: int, K: int, hidden: int, like: torch.Tensor):
        most = B * K if like.device.type != "cpu" else max(1, PIECE_ELEMENTS * torch.get_num_threads() // hidden)
        if K <= most:
            self.images = min(B, most // K)  # whole images per piece
            spans = [(b * K, min(self.images, B - b) * K, b, min(self.images, B - b))
                     for b in range(0, B, self.images)]  # fmt: skip
        else:
            self.images = 1
            spans = [(b * K + s, min(most, K - s), b, 1) for b in range(B) for s in range(0, K, most)]
        width = max(n for _, n, _, _ in spans)
        N = B * K
        self.products = torch.empty(16, N, dtype=like.dtype, device=like.device)
        self.columns = torch.empty(9 + self.images, N, dtype=like.dtype, device=like.device)
        image = torch.arange(N, device=like.device) // K % self.images
        self.columns[9:] = image == torch.arange(self.images, device=like.device)[:, None]
        self.out = torch.empty(4, N, dtype=like.dtype, device=like.device)
        self.quaternions = torch.empty(2, 4, N, dtype=like.dtype, device=like.device)  # each layer's output
        self.affine = torch.empty(B, 4, K, dtype=like.dtype, device=like.device)
        self.activations = torch.empty(2, hidden + 1, width, dtype=like.dtype, device=like.device)
        self.activations[:, hidden] = 1  # written once: the layers write the rows above
        #: per piece: (first image, images, first layer's input, activation buffers (all rows, the rows
        #: written), the piece's columns of the output)
        self.pieces = [
            (b, m, self.columns[6 : 9 + m, s : s + n],
             [(a[:, :n], a[:hidden, :n]) for a in self.activations], self.out[:, s : s + n])
            for s, n, b, m in spans
        ]  # fmt: skip

    def output_for(self, q: torch.Tensor) -> torch.Tensor:
        """The quaternion buffer ``(4, B K)`` a layer writes its output into: the one its input ``q`` is not."""
        first, second = self.quaternions
        return second if q.data_ptr() == first.data_ptr() else first


def _with_bias(linear: nn.Linear) -> torch.Tensor:
    """``[W | b]`` ``(out, in + 1)``: the layer as one product with an input that ends in a row of ones."""
    return torch.cat([linear.weight, linear.bias[:, None]], dim=1)


def _half_turn(
    v_j: torch.Tensor, v_k: torch.Tensor, phi: torch.Tensor, inverse: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """``cos(a/2)``, ``sin(a/2)`` of a coupling's turn and its ``log |det J|`` (module docstring), from the
    conditioner's output: ``v``'s coordinates ``v_j, v_k`` in the circle's plane and the angle ``phi``, each
    ``(N,)``."""
    norm = torch.linalg.vector_norm(torch.stack([v_j, v_k]), dim=0)  # its gradient at 0 (the identity start) is 0
    scale = W_MAX / (1 + norm)
    w_j, w_k = v_j * scale, v_k * scale
    half = 0.5 * phi
    cos, sin = half.cos(), half.sin()
    if inverse:  # u = exp(-i phi/2) + w exp(i phi/2)
        re = torch.addcmul(cos * (1 + w_j), w_k, sin, value=-1)
        im = torch.addcmul(sin * (w_j - 1), w_k, cos)
    else:  # u = exp(i phi/2) (1 - w)
        re = torch.addcmul(cos * (1 - w_j), w_k, sin)
        im = torch.addcmul(sin * (1 - w_j), w_k, cos, value=-1)
    u_sq = torch.addcmul(re * re, im, im)  # |u|^2 >= (1 - |w|)^2 > 0
    log_det = ((1 - (norm * scale).square()) / u_sq).log()  # log(1 - |w|^2) - log |u|^2
    inv = u_sq.rsqrt()
    return re * inv, im * inv, log_det


def _half_turn_in_place(
    v_j: torch.Tensor, v_k: torch.Tensor, phi: torch.Tensor, inverse: bool
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """:func:`_half_turn` without autograd, in fewer new tensors (each a pass over memory): ``v_j`` and
    ``v_k`` are overwritten."""
    norm = (v_j * v_j).addcmul_(v_k, v_k).sqrt_()
    scale = norm.add(1).reciprocal_().mul_(W_MAX)
    one_minus_w_sq = norm.mul_(scale).square_().neg_().add_(1)  # 1 - |w|^2
    w_j, w_k = v_j.mul_(scale), v_k.mul_(scale)
    cos = (0.5 * phi).cos_()
    sin = (0.5 * phi).sin_()
    if inverse:
        re = (w_j + 1).mul_(cos).addcmul_(w_k, sin, value=-1)
        im = w_j.sub_(1).mul_(sin).addcmul_(w_k, cos)
    else:
        re = (1 - w_j).mul_(cos).addcmul_(w_k, sin)
        im = w_j.neg_().add_(1).mul_(sin).addcmul_(w_k, cos, value=-1)
    u_sq = (re * re).addcmul_(im, im)
    log_det = one_minus_w_sq.div_(u_sq).log_()
    inv = u_sq.rsqrt_()
    return re.mul_(inv), im.mul_(inv), log_det


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
            raise ConfigError(f"column must be 0, 1 or 2, got {column!r}")
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
        # rows c_j, c_k, c_i of the rotation from the products q_a q_b (module docstring), and q -> q e_i;
        # not in the state dict (constants of the layer: checkpoints keep their keys)
        form = _ROTATION_FORM[:, [self.j, self.k, self.i]].permute(1, 0, 2).reshape(9, 16)
        self.register_buffer("_form", form.float(), persistent=False)
        self.register_buffer("_times_axis", _times_axis(self.i).float(), persistent=False)
        # row r of q e_i is sign * q[column]: (column, sign) per row
        self._turned_rows = [(int(row.abs().argmax()), float(row[row.abs().argmax()])) for row in _times_axis(self.i)]

    def map_quaternions(
        self, q: torch.Tensor, z: torch.Tensor, inverse: bool = False, buffers: _Buffers | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The layer (or its inverse) on unit quaternions ``q (4, B, K)`` (components first) for conditions
        ``z (B, F)``: the new quaternions ``(4, B, K)`` and ``log |det J| (B, K)`` (module docstring).
        ``buffers`` (only without autograd): where the products and activations are written."""
        _, B, K = q.shape
        q = q.reshape(4, B * K)  # [4, N]: image-major columns
        if buffers is None:
            products = (q[:, None] * q[None]).view(16, -1)  # q_a q_b
        else:  # a kept buffer: a fresh megabyte costs an allocation and, often, page faults
            products = buffers.products
            torch.mul(q[:, None], q[None], out=products.view(4, 4, -1))
        out, columns = self._conditioner(products, z, B, K, buffers)  # [4, N] (v, phi), [9 (+ images), N]
        v, phi = out[:3], out[3]
        # v's coordinates along c_j and c_k, then w = v_plane W_MAX / (1 + |v_plane|) in the circle's plane
        v_j = (columns[0] * v[0]).addcmul_(columns[1], v[1]).addcmul_(columns[2], v[2])  # [N]
        v_k = (columns[3] * v[0]).addcmul_(columns[4], v[1]).addcmul_(columns[5], v[2])
        half_turn = _half_turn if buffers is None else _half_turn_in_place
        cos_half, sin_half, log_det = half_turn(v_j, v_k, phi, inverse)  # of the turn's angle a
        if buffers is None:  # q (cos a/2 + sin a/2 e_i)
            q = torch.addcmul(q * cos_half, torch.mm(self._times_axis.to(q.dtype), q), sin_half)
        else:  # the same into a kept buffer, q e_i read as signed rows of q (a product with 4 rows is slow)
            new = torch.mul(q, cos_half, out=buffers.output_for(q))
            for row, (column, sign) in enumerate(self._turned_rows):
                new[row].addcmul_(q[column], sin_half, value=sign)
            q = new
        return q.view(4, B, K), log_det.view(B, K)

    def _conditioner(
        self, products: torch.Tensor, z: torch.Tensor, B: int, K: int, buffers: _Buffers | None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """The conditioner's output ``(4, N)`` (rows ``v``, ``phi``) and the rotation's columns ``c_j, c_k,
        c_i`` as rows ``(9, N)`` (with ``buffers`` then the one-hot rows of :class:`_Buffers`), from the
        products ``q_a q_b`` ``(16, N)`` of ``N = B K`` rotations.

        The first layer is ``W c_i`` plus the image's condition term. With ``buffers`` it is one product per
        piece of the rotations with ``[W | condition terms of the piece's images]`` and the rows ``c_i`` and
        one-hot image codes; each later bias is the last column of its layer's matrix (its input's row of
        ones), so a layer is one product and one in-place rectification. On a CPU the pieces hold
        :data:`PIECE_ELEMENTS` activations per thread, which stay in the cores' caches from one layer to the
        next."""
        form = self._form.to(products.dtype)
        condition = self.from_condition(z)  # [B, H]
        linears = [layer for layer in self.layers if isinstance(layer, nn.Linear)]
        H = self.hidden
        if buffers is None:
            columns = torch.mm(form, products)  # [9, N]
            h = torch.mm(self.from_column.weight, columns[6:]).view(H, B, K) + condition.T[:, :, None]
            h = h.relu_().view(H, -1)  # [H, N]
            for layer in linears:
                h = torch.addmm(layer.bias[:, None], layer.weight, h).relu_()
            return torch.addmm(self.out.bias[:, None], self.out.weight, h), columns  # [4, N]
        columns, out = buffers.columns, buffers.out
        torch.mm(form, products, out=columns[:9])
        weights = [_with_bias(layer) for layer in (*linears, self.out)]  # [out, in + 1]
        per_image = torch.cat([self.from_column.weight.expand(len(z), -1, -1), condition[:, :, None]], dim=2)
        for image, images, x, activations, piece_out in buffers.pieces:
            if images == 1:
                first = per_image[image]  # [H, 4]
            else:
                first = torch.cat([self.from_column.weight, condition[image : image + images].T], dim=1)  # [H, 3 + m]
            h, rows = activations[0]
            torch.mm(first, x, out=rows).relu_()  # the row of ones below stays
            for index, weight in enumerate(weights[:-1], 1):
                nxt, rows = activations[index % 2]
                torch.mm(weight, h, out=rows).relu_()
                h = nxt
            torch.mm(weights[-1], h, out=piece_out)
        return out, columns

    def _via_matrices(self, R: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        q, log_det = self.map_quaternions(SO3Flow._quaternions(R, z, expand=True), z, inverse)
        return _rotations(q), log_det  # [B, K, 3, 3], [B, K]

    def forward(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R)`` and ``log |det J_T(R)|`` for rotations ``R (B, K, 3, 3)`` and conditions ``z (B, F)``."""
        return self._via_matrices(R, z, inverse=False)

    def inverse(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T^{-1}(R)`` and ``log |det J_{T^{-1}}(R)|``, exactly."""
        return self._via_matrices(R, z, inverse=True)


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

    def map_quaternions(
        self, q: torch.Tensor, z: torch.Tensor, inverse: bool = False, buffers: _Buffers | None = None
    ) -> tuple[torch.Tensor, torch.Tensor]:
        """As :meth:`MobiusCoupling.map_quaternions`, on ``q (4, B, K)`` or ``(4, K)`` (the same rotations for
        every condition): ``(4, B, K)`` and ``log |det J| (B, K)``. ``buffers``: as the coupling's."""
        A = self.to_matrix(z).reshape(-1, 4, 4)  # [B, 4, 4]
        # traceless: exp(A - t I) = exp(-t) exp(A) is the same map q -> W q / |W q|, with det W = 1
        A = A - A.diagonal(dim1=-2, dim2=-1).mean(-1)[:, None, None] * torch.eye(4, dtype=A.dtype, device=A.device)
        if inverse:
            A = -A
        W = torch.linalg.matrix_exp(A)
        q_images = q.expand(len(A), *q.shape) if q.ndim == 2 else q.transpose(0, 1)  # [B, 4, K]
        if buffers is None:
            Wq = torch.bmm(W, q_images).transpose(0, 1)  # [4, B, K]
        else:  # kept buffers, as the couplings'
            Wq = torch.bmm(W, q_images, out=buffers.affine).transpose(0, 1)
        sq = torch.addcmul(Wq[0] * Wq[0], Wq[1], Wq[1]).addcmul_(Wq[2], Wq[2]).addcmul_(Wq[3], Wq[3])  # |W q|^2
        log_det = -2 * sq.log()  # log det W - 4 log |W q|, det W = 1  # [B, K]
        if buffers is None:
            return (Wq * sq.rsqrt()).contiguous(), log_det
        return torch.mul(Wq, sq.rsqrt(), out=buffers.output_for(q).view(Wq.shape)), log_det

    def _via_matrices(self, R: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        q, log_det = self.map_quaternions(SO3Flow._quaternions(R, z), z, inverse)
        return _rotations(q), log_det

    def forward(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R)`` and ``log |det J_T(R)|`` for ``R (B, K, 3, 3)`` and ``z (B, F)``."""
        return self._via_matrices(R, z, inverse=False)

    def inverse(self, R: torch.Tensor, z: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T^{-1}(R)`` and ``log |det J_{T^{-1}}(R)|``, exactly (``W^{-1} = exp(-A)``)."""
        return self._via_matrices(R, z, inverse=True)


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
    def _quaternions(R: torch.Tensor, z: torch.Tensor, expand: bool = False) -> torch.Tensor:
        """The unit quaternions ``(4, K)`` (shared; ``(4, B, K)`` with ``expand``) or ``(4, B, K)`` of
        rotations ``(K, 3, 3)`` or ``(B, K, 3, 3)``, in ``z``'s dtype."""
        if R.ndim != 3 and (R.ndim != 4 or R.shape[0] != len(z)) or R.shape[-2:] != (3, 3):
            raise ConfigError(f"rotations must have shape (K, 3, 3) or ({len(z)}, K, 3, 3), got {tuple(R.shape)}")
        q = _quaternions(R.to(z))
        return q[:, None].expand(4, len(z), q.shape[1]) if expand and q.ndim == 2 else q

    def _work_buffers(self, B: int, K: int, like: torch.Tensor) -> _Buffers | None:
        """The work buffers (:class:`_Buffers`) for ``B x K`` rotations without autograd, kept for the next call
        with the same key in the same thread; ``None`` with autograd. Per thread: two threads evaluating one
        model at once, as a server's request handlers may, never share one. One key at a time per thread: a
        sweep uses one chunk size, its last chunk another. A buffer made under ``torch.inference_mode``
        (Lightning's test loop) cannot be written outside it (``torch.no_grad``, a prediction afterwards), so
        the mode is part of the key."""
        if torch.is_grad_enabled():
            return None
        key = (B, K, like.dtype, like.device, torch.is_inference_mode_enabled())
        per_thread = self.__dict__.setdefault("_buffers_by_thread", {})
        kept = per_thread.get(threading.get_ident())
        if kept is None or kept[0] != key:
            kept = (key, _Buffers(B, K, self.hidden, like))
            per_thread[threading.get_ident()] = kept
        return kept[1]

    def _run(self, q: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
        """Every layer (backwards with ``inverse``) on quaternions ``(4, B, K)`` or ``(4, K)`` (shared): the
        final ones ``(4, B, K)`` and the summed ``log |det J|`` ``(B, K)``."""
        B, K = len(z), q.shape[-1]
        if K == 0:
            return z.new_zeros(4, B, 0), z.new_zeros(B, 0)
        buffers = self._work_buffers(B, K, z)
        total = None
        for layer in reversed(self.layers) if inverse else self.layers:
            if q.ndim == 2 and isinstance(layer, MobiusCoupling):
                q = q[:, None].expand(4, B, K)
            q, log_det = layer.map_quaternions(q, z, inverse, buffers)
            total = log_det if total is None else total + log_det
        return q, total

    def log_prob(self, z: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
        """The exact log density ``(B, K)`` (Haar measure of volume ``pi^2``) at rotations ``R`` ``(K, 3, 3)``
        (shared) or ``(B, K, 3, 3)`` for conditions ``z (B, F)``."""
        return self._run(self._quaternions(R, z), z, inverse=True)[1] + LOG_UNIFORM_DENSITY

    def transform(self, z: torch.Tensor, R0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        """``T(R0)`` ``(B, K, 3, 3)`` and ``log |det J_T(R0)|`` ``(B, K)`` (the forward direction)."""
        q, total = self._run(self._quaternions(R0, z, expand=True), z, inverse=False)
        return _rotations(q), total

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
        width = CPU_CALL_WIDTH if output.device.type == "cpu" else self.flow.hidden
        return FlowDistribution(output, self.flow.log_prob, self.flow.sample, width=width)

    def loss(self, output: torch.Tensor, rotation: torch.Tensor, grid_level: int | None = None) -> torch.Tensor:
        """The negative log likelihood ``(B,)`` of ``rotation (B, 3, 3)``, exact (``grid_level`` unused)."""
        return -self.flow.log_prob(output, rotation[:, None])[:, 0]

    def set_loss(
        self, output: torch.Tensor, rotations: torch.Tensor, mask: torch.Tensor, grid_level: int
    ) -> torch.Tensor:
        """The negative log likelihood averaged over each image's equivalent ``rotations (B, M, 3, 3)``
        where ``mask (B, M)``: one batched pass of the flow for every rotation of the set."""
        check_rotation_set(output, rotations, mask)
        real = mask.to(output)
        log_p = self.flow.log_prob(output, fill_padding(rotations, mask).to(output))  # [B, M]
        return -(log_p * real).sum(1) / real.sum(1)
