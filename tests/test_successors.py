"""The methods that came after I2S: direct Wigner-D regression and the normalizing flow on SO(3).

Quick tier (each test well under a few seconds). The Wigner-D target against e3nn itself, the
regression loss's equivariance and (non-)invariance to equivalent labels, the flow's normalisation on
a fine grid, its log density against the change of variables computed by autograd, its exact inverse,
and its exact samples against its density by a two-sample test. End-to-end runs of both methods are in
tests/test_methods_entry.py, DDP in tests/test_scaling.py.
"""

from __future__ import annotations

import math

import pytest
import torch
from e3nn import o3
from scipy.stats import chi2_contingency
from torch import nn

from conftest import haar_rotations
from image2sphere.distributions.base import LOG_UNIFORM_DENSITY
from image2sphere.distributions.flow import FlowDistribution
from image2sphere.distributions.fourier import SO3Distribution, fourier_grid_nll, fourier_grid_set_nll
from image2sphere.nn.base import mean_loss_over_set
from image2sphere.nn.so3_flow import MobiusCoupling, QuaternionAffine, RotationFlow, SO3Flow, mobius_circle
from image2sphere.nn.wigner_regression import WignerDRegression, wigner_mse, wigner_target
from image2sphere.so3.grid import so3_healpix_grid, so3_healpix_nearest_index
from image2sphere.so3.groups import rotation_group
from image2sphere.so3.rotations import geodesic_distance_deg, rotvec_to_matrix
from image2sphere.so3.wigner import default_dtype, left_translate_so3_coeffs, n_so3_coeffs
from test_mixed_precision import TinyEncoder  # a 4-channel conv stand-in for the ResNet


# ------------------------------------------------------------------ Wigner-D regression
@pytest.mark.parametrize("lmax", [1, 4])
def test_wigner_target_is_e3nns_wigner_d_of_the_rotation(lmax):
    R = haar_rotations(5, seed=lmax)
    with default_dtype(torch.float64):
        angles = o3.matrix_to_angles(R)  # e3nn's own angles: independent of our matrix_to_angles
        expected = torch.cat([o3.wigner_D(l, *angles).flatten(-2) for l in range(lmax + 1)], dim=-1)
    target = wigner_target(lmax, R)
    assert target.shape == (5, n_so3_coeffs(lmax))
    torch.testing.assert_close(target, expected, atol=1e-10, rtol=0)
    # degree 1 is the rotation itself in e3nn's (y, z, x) basis: orthogonal with determinant 1
    D1 = target[:, 1:10].reshape(5, 3, 3)
    torch.testing.assert_close(D1 @ D1.transpose(1, 2), torch.eye(3, dtype=torch.float64).expand(5, 3, 3))


def test_wigner_target_read_as_coefficients_peaks_at_its_rotation():
    lmax, level = 6, 3
    R = haar_rotations(4, seed=1)
    mode = SO3Distribution(wigner_target(lmax, R), lmax).mode(level)  # grid argmax of the signal
    nearest = so3_healpix_grid(level, dtype=torch.float64)[so3_healpix_nearest_index(R, level)]
    torch.testing.assert_close(mode, nearest)
    assert (geodesic_distance_deg(mode, R) < 6).all()


def test_wigner_loss_is_equivariant_and_zero_only_at_the_target():
    lmax = 3
    torch.manual_seed(0)
    c = torch.randn(3, n_so3_coeffs(lmax), dtype=torch.float64)
    R, g = haar_rotations(3, seed=2), haar_rotations(1, seed=3)[0]
    loss = wigner_mse(c, wigner_target(lmax, R))
    moved = wigner_mse(left_translate_so3_coeffs(c, g, lmax), wigner_target(lmax, g @ R))  # c^l -> D^l(g) c^l, R -> gR
    torch.testing.assert_close(moved, loss)
    assert (loss > 0.1).all()
    assert wigner_mse(wigner_target(lmax, R), wigner_target(lmax, R)).abs().max() < 1e-12


def _wigner_net(**kwargs) -> WignerDRegression:
    return WignerDRegression(TinyEncoder(), image_size=16, lmax=2, sphere_channels=4, so3_channels=2,
                             harmonic_hidden=4, **kwargs).double()  # fmt: skip


def test_wigner_loss_depends_on_the_equivalent_label_but_its_set_average_does_not():
    """A single label of a symmetric object gives a different loss for each equivalent rotation (the
    regression cannot represent a symmetry); averaged over the whole set it is the same whichever
    rotation of the set is the label, and it is the expectation of the single-label loss."""
    net = _wigner_net()
    torch.manual_seed(1)
    c = torch.randn(2, n_so3_coeffs(2), dtype=torch.float64)
    R = haar_rotations(2, seed=4)
    S = rotation_group("T").to(torch.float64)  # the tetrahedron's 12 rotations
    single = torch.stack([net.loss(c, R @ s, grid_level=1) for s in S], dim=1)  # [B, 12]
    assert (single.max(1).values - single.min(1).values > 0.05).all()
    mask = torch.ones(2, 12, dtype=torch.bool)
    as_label = net.set_loss(c, R[:, None] @ S, mask, 1)  # R S_k
    other = net.set_loss(c, (R @ S[5])[:, None] @ S, mask, 1)  # another representative: the same set
    torch.testing.assert_close(other, as_label)
    torch.testing.assert_close(as_label, single.mean(1))
    torch.testing.assert_close(as_label, mean_loss_over_set(net.loss, c, R[:, None] @ S, mask, 1))


def test_wigner_loss_adds_the_distribution_loss_with_its_weight_and_checks_its_weights():
    R = haar_rotations(3, seed=5)
    torch.manual_seed(2)
    c = torch.randn(3, n_so3_coeffs(2), dtype=torch.float64)
    plain, mixed = _wigner_net(), _wigner_net(regression_weight=2.0, distribution_weight=0.5)
    expected = 2 * plain.loss(c, R, 2) + 0.5 * fourier_grid_nll(c, 2, R, 2)
    torch.testing.assert_close(mixed.loss(c, R, 2), expected)
    padded = torch.cat([R[:, None], R[:, None]], 1)
    mask = torch.tensor([[True, False]] * 3)
    torch.testing.assert_close(mixed.set_loss(c, padded, mask, 2), expected)
    for bad in ({"regression_weight": 0}, {"distribution_weight": -1}, {"distribution_weight": float("nan")}):
        with pytest.raises(ValueError, match=f"model.net.{next(iter(bad))}"):
            _wigner_net(**bad)


# ------------------------------------------------------------------ the flow
def _random_flow(scale: float, seed: int = 0, blocks: int = 2, dim: int = 5) -> tuple[SO3Flow, torch.Tensor]:
    """A float64 flow with every parameter drawn at ``scale`` (not the identity it starts as) and 3 conditions."""
    torch.manual_seed(seed)
    flow = SO3Flow(dim, blocks=blocks, hidden=16).double()
    with torch.no_grad():
        for p in flow.parameters():
            p.normal_(0, scale)
    return flow, torch.randn(3, dim, dtype=torch.float64)


def test_mobius_map_keeps_the_circle_and_its_inverse_is_minus_w():
    torch.manual_seed(3)
    theta = torch.rand(50, dtype=torch.float64) * 2 * math.pi
    x = torch.stack([theta.cos(), theta.sin(), torch.zeros_like(theta)], -1)  # the circle in the xy-plane
    w = torch.tensor([0.5, -0.3, 0.0], dtype=torch.float64)
    y, log_det = mobius_circle(x, w)
    torch.testing.assert_close(y.norm(dim=-1), torch.ones(50, dtype=torch.float64))
    assert y[:, 2].abs().max() < 1e-15
    torch.testing.assert_close(mobius_circle(y, -w)[0], x)
    # the derivative of the angle, by central differences
    h = 1e-6

    def angle(t):  # noqa: E306
        p = mobius_circle(torch.stack([t.cos(), t.sin(), torch.zeros_like(t)], -1), w)[0]
        return torch.atan2(p[:, 1], p[:, 0])

    d = torch.remainder(angle(theta + h) - angle(theta - h) + math.pi, 2 * math.pi) - math.pi
    torch.testing.assert_close(log_det, (d / (2 * h)).log(), atol=1e-6, rtol=0)


def test_flow_density_integrates_to_one_on_a_fine_grid():
    """The grid mean of ``exp(log p) * pi^2`` (the integral by the equal-volume HEALPix quadrature) is 1 to
    2e-3 at level 4, and the largest error shrinks at least fourfold from level 3 to 4 (a converging
    quadrature, not a constant offset)."""
    flow, z = _random_flow(0.15)
    errors = []
    for level in (3, 4):
        grid = so3_healpix_grid(level, dtype=torch.float64)
        with torch.no_grad():
            log_p = torch.cat([flow.log_prob(z, grid[i : i + 65536]) for i in range(0, len(grid), 65536)], 1)
        assert (log_p.max(1).values - LOG_UNIFORM_DENSITY > 3).all()  # far from uniform: 20 times its density
        errors.append((log_p.exp().mean(1) * math.pi**2 - 1).abs())
    assert (errors[1] < 2e-3).all(), errors[1]
    assert errors[1].max() < errors[0].max() / 4, errors  # the sharpest of the three converges


def _haar_log_jacobian(flow: SO3Flow, z: torch.Tensor, R0: torch.Tensor) -> torch.Tensor:
    """``log |det dT|`` at ``R0 (3, 3)`` for condition ``z (1, F)`` by autograd: the 3 x 3 Jacobian of
    ``w -> log(T(R0)^T T(R0 exp(w)))`` at 0, in right-trivialised coordinates (Haar measure: unit density)."""
    T0 = flow.transform(z, R0[None])[0][0, 0]

    def moved(w):
        return flow.transform(z, (R0 @ rotvec_to_matrix(w))[None])[0][0, 0]  # [3, 3]

    dT = torch.autograd.functional.jacobian(moved, torch.zeros(3, dtype=torch.float64))  # [3, 3, 3 (w)]
    X = torch.einsum("ji,jka->aik", T0, dT)  # T0^T dT/dw_a: skew  [a, 3, 3]
    J = torch.stack([X[:, 2, 1], X[:, 0, 2], X[:, 1, 0]], dim=0)  # vee, columns a  [3, 3]
    return torch.linalg.det(J).abs().log()


def test_flow_log_density_is_the_change_of_variables():
    flow, z = _random_flow(0.3, seed=1)
    R0 = haar_rotations(4, seed=6)
    for b in range(2):
        R, log_det = flow.transform(z[b : b + 1], R0)
        log_p = flow.log_prob(z[b : b + 1], R)  # backwards through every layer's inverse
        for k in range(4):
            reference = LOG_UNIFORM_DENSITY - _haar_log_jacobian(flow, z[b : b + 1], R0[k])
            torch.testing.assert_close(log_p[0, k], reference, atol=1e-8, rtol=0)
            torch.testing.assert_close(log_det[0, k], -(log_p[0, k] - LOG_UNIFORM_DENSITY), atol=1e-8, rtol=0)


def test_flow_layers_invert_exactly_and_start_as_the_identity():
    flow, z = _random_flow(0.3, seed=2)
    R0 = haar_rotations(6, seed=7).expand(3, 6, 3, 3)
    for layer in flow.layers:
        R1, forward = layer(R0, z)
        back, inverse = layer.inverse(R1, z)
        torch.testing.assert_close(back, R0, atol=1e-10, rtol=0)
        torch.testing.assert_close(inverse, -forward, atol=1e-10, rtol=0)
        torch.testing.assert_close(R1.transpose(-1, -2) @ R1, torch.eye(3, dtype=torch.float64).expand_as(R1))
        torch.testing.assert_close(torch.linalg.det(R1), torch.ones(3, 6, dtype=torch.float64))
    fresh = SO3Flow(5, blocks=1).double()
    assert all(isinstance(m, (MobiusCoupling, QuaternionAffine)) for m in fresh.layers)
    R, log_det = fresh.transform(z, R0)
    torch.testing.assert_close(R, R0)
    torch.testing.assert_close(fresh.log_prob(z, R0), torch.full((3, 6), LOG_UNIFORM_DENSITY, dtype=torch.float64))


def test_affine_layer_ignores_the_trace_of_its_matrix_so_a_large_one_cannot_overflow():
    """Quick. ``q -> W q / |W q|`` divides out any scale of ``W = exp(A)``: adding ``t I`` to ``A`` gives the same
    rotations and the same log Jacobian. With ``t = 1000`` the full ``exp(A)`` overflows float64 (``e^1000``);
    the layer, which drops the trace, stays finite and equal to the layer without it."""
    torch.manual_seed(0)
    layer = QuaternionAffine(5).double()
    nn.init.normal_(layer.to_matrix.weight, std=0.3)
    z, R0 = torch.randn(2, 5, dtype=torch.float64), haar_rotations(7, seed=3).expand(2, 7, 3, 3)
    plain = [layer(R0, z), layer.inverse(R0, z)]
    with torch.no_grad():
        layer.to_matrix.bias += 1000 * torch.eye(4, dtype=torch.float64).flatten()
    assert not torch.isfinite(torch.linalg.matrix_exp(layer.to_matrix(z).reshape(-1, 4, 4))).all()
    for (R, log_det), (R_plain, log_det_plain) in zip([layer(R0, z), layer.inverse(R0, z)], plain, strict=True):
        assert torch.isfinite(R).all() and torch.isfinite(log_det).all()
        torch.testing.assert_close(R, R_plain)
        torch.testing.assert_close(log_det, log_det_plain)


def _binned(R: torch.Tensor) -> torch.Tensor:
    """Counts of rotations ``(n, 3, 3)`` in the 72 cells of the level-0 grid (nearest point)."""
    return torch.bincount(so3_healpix_nearest_index(R, 0), minlength=72)


def test_flow_samples_follow_its_density_by_a_two_sample_test():
    """Exact samples (uniform rotations through the flow) against draws from the density itself on the
    level-4 grid, binned into the level-0 grid's 72 cells: a chi-square two-sample test accepts them,
    and rejects samples of a different flow (the test has power)."""
    flow, z = _random_flow(0.15, seed=3)
    dist = FlowDistribution(z[:1], flow.log_prob, flow.sample, width=16)
    gen = torch.Generator().manual_seed(0)
    exact = dist.exact_sample(6000, generator=gen)[0]  # [n, 3, 3]
    grid = so3_healpix_grid(4, dtype=torch.float64)
    with torch.no_grad():
        log_p = dist.unnormalized_log_density(grid)[0]  # the density at the grid's equal-volume points
    gen = torch.Generator().manual_seed(1)
    pick = torch.multinomial(torch.softmax(log_p, 0), 6000, replacement=True, generator=gen)
    on_grid = grid[pick]
    counts = torch.stack([_binned(exact), _binned(on_grid)]).numpy()
    keep = counts.sum(0) > 0
    p_same = chi2_contingency(counts[:, keep])[1]
    assert p_same > 1e-3, p_same
    other, z2 = _random_flow(0.15, seed=4)
    different = other.sample(z2[:1], 6000, generator=torch.Generator().manual_seed(2))[0]
    counts = torch.stack([_binned(exact), _binned(different)]).numpy()
    keep = counts.sum(0) > 0
    assert chi2_contingency(counts[:, keep])[1] < 1e-6


def test_flow_network_is_uniform_at_the_start_normalised_and_trained_by_the_exact_nll():
    net = RotationFlow(TinyEncoder(), image_size=16, condition_dim=6, blocks=1, hidden=8).double()
    images = torch.randn(2, 3, 16, 16, dtype=torch.float64)
    output = net(images)
    dist = net.output_distribution(output)
    R = haar_rotations(5, seed=8)
    assert dist.has_exact_density
    torch.testing.assert_close(dist.exact_log_normalizer(), torch.zeros(2, dtype=torch.float64))
    torch.testing.assert_close(dist.exact_log_density(R), torch.full((2, 5), LOG_UNIFORM_DENSITY, dtype=torch.float64))
    with torch.no_grad():
        for p in net.flow.parameters():
            p.normal_(0, 0.2)
    dist = net.output_distribution(output)
    labels = R[:2]
    loss = net.loss(output, labels)
    torch.testing.assert_close(loss, -dist.exact_log_density(labels[:, None])[:, 0])
    loss.sum().backward()
    assert net.encoder.conv.weight.grad.abs().sum() > 0  # the image conditions the flow
    rotations = torch.stack([R[:3], R[2:]])  # [2, 3, 3, 3]
    mask = torch.tensor([[True, True, False], [True, True, True]])
    torch.testing.assert_close(
        net.set_loss(output, rotations, mask, 1), mean_loss_over_set(net.loss, output, rotations, mask, 1)
    )
    with pytest.raises(ValueError, match="rotation must have shape"):
        net.loss(output, R[:3])


def test_set_losses_refuse_a_padded_first_rotation_and_take_it_reordered():
    """A set whose first entry is padding (NaN here) with a real entry after it: the Wigner-D regression's,
    the flow's and I2S's set losses (which read padding as the image's first rotation) and the generic mean
    over the set refuse it naming the rule (mask[:, 0] must be True), rather than reading the NaN as a
    rotation; the same set with its real rotations first gives a finite loss."""
    R = haar_rotations(4, seed=9).reshape(2, 2, 3, 3)
    mask = torch.tensor([[False, True], [True, True]])
    padded = R.masked_fill(~mask[..., None, None], math.nan)
    wigner = _wigner_net()
    flow = RotationFlow(TinyEncoder(), image_size=16, condition_dim=6, blocks=1, hidden=8).double()
    with torch.no_grad():
        for p in flow.flow.parameters():
            p.normal_(0, 0.2)
    torch.manual_seed(3)
    c = torch.randn(2, n_so3_coeffs(2), dtype=torch.float64)
    losses = {
        "wigner": lambda r, m: wigner.set_loss(c, r, m, 1),
        "flow": lambda r, m: flow.set_loss(flow(torch.randn(2, 3, 16, 16, dtype=torch.float64)), r, m, 1),
        "mean_loss_over_set": lambda r, m: mean_loss_over_set(wigner.loss, c, r, m, 1),
        "i2s": lambda r, m: fourier_grid_set_nll(c, 2, r, m, 1),
    }
    for name, set_loss in losses.items():
        with pytest.raises(ValueError, match=r"mask\[:, 0\] must be True"):
            set_loss(padded, mask)
        assert torch.isfinite(set_loss(padded.flip(1), mask.flip(1))).all(), name


def _reference_layer(layer, R: torch.Tensor, z: torch.Tensor, inverse: bool) -> tuple[torch.Tensor, torch.Tensor]:
    """One layer on rotation matrices ``R (B, K, 3, 3)`` as the module docstring writes it, independent of the
    layers' quaternion arithmetic: a coupling moves column ``j`` by the disk automorphism in 3-D, turns it
    about ``c_i`` (a cross product), renormalises and completes the frame by a cross product; the affine layer
    maps the quaternion of each matrix. (The formulas of the flow before it was evaluated in quaternions.)"""
    from image2sphere.nn.so3_flow import W_MAX
    from image2sphere.so3.rotations import matrix_to_quaternion, quaternion_to_matrix

    if isinstance(layer, QuaternionAffine):
        A = layer.to_matrix(z).reshape(-1, 4, 4) * (-1 if inverse else 1)
        Wq = (torch.linalg.matrix_exp(A)[:, None] @ matrix_to_quaternion(R, "wxyz")[..., None])[..., 0]  # [B, K, 4]
        log_det = A.diagonal(dim1=-2, dim2=-1).sum(-1)[:, None] - 4 * Wq.norm(dim=-1).log()
        return quaternion_to_matrix(Wq, "wxyz"), log_det
    axis, x = R[..., layer.i], R[..., layer.j]  # [B, K, 3]
    h = torch.relu(layer.from_condition(z)[:, None] + axis @ layer.from_column.weight.T)
    for module in layer.layers:
        h = module(h)
    out = layer.out(h)
    v = out[..., :3] - (out[..., :3] * axis).sum(-1, keepdim=True) * axis  # onto the circle's plane
    w = v * (W_MAX / (1 + v.norm(dim=-1, keepdim=True)))
    phi = out[..., 3:]

    def disk(x, w):  # h_w(x) and log |h_w'(x)|
        scale = (1 - (w * w).sum(-1, keepdim=True)) / ((x - w) ** 2).sum(-1, keepdim=True)
        return scale * (x - w) - w, scale[..., 0].log()

    def turn(x, angle):
        return angle.cos() * x + angle.sin() * torch.linalg.cross(axis, x, dim=-1)

    if inverse:
        y, log_det = disk(turn(x, -phi), -w)
    else:
        y, log_det = disk(x, w)
        y = turn(y, phi)
    y = torch.nn.functional.normalize(y - (y * axis).sum(-1, keepdim=True) * axis, dim=-1)
    columns = [axis] * 3
    columns[layer.j], columns[layer.k] = y, torch.linalg.cross(axis, y, dim=-1)
    return torch.stack(columns, dim=-1), log_det


def _reference_log_prob(flow: SO3Flow, z: torch.Tensor, R: torch.Tensor) -> torch.Tensor:
    R = R.expand(len(z), *R.shape[-3:])  # [B, K, 3, 3]
    total = torch.zeros(R.shape[:2], dtype=R.dtype)
    for layer in reversed(flow.layers):
        R, log_det = _reference_layer(layer, R, z, inverse=True)
        total = total + log_det
    return total + LOG_UNIFORM_DENSITY


def _reference_transform(flow: SO3Flow, z: torch.Tensor, R: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    total = torch.zeros(R.shape[:2], dtype=R.dtype)
    for layer in flow.layers:
        R, log_det = _reference_layer(layer, R, z, inverse=False)
        total = total + log_det
    return R, total


def test_flow_evaluated_in_quaternions_equals_the_matrix_form_in_float64(monkeypatch):
    """Quick (0.04 s). At random parameters (a block, two hidden layers per conditioner, 3 images), float64: the
    log density, the forward map and its log-determinant equal the matrix-form reference (the layers as the
    module docstring writes them) to 1e-10, with autograd (also every gradient) and without it, where the
    conditioners run on pieces of the rotations: whole images, several images per piece with a narrower last
    piece, and parts of one image (pieces made small here), and through a grid sweep whose calls do not divide
    the grid. Checkpoints keep their keys: the state dict holds the parameters only."""
    from image2sphere.nn import so3_flow

    torch.manual_seed(13)
    flow = SO3Flow(5, blocks=1, hidden=16, depth=3).double()
    with torch.no_grad():
        for p in flow.parameters():
            p.normal_(0, 0.3)
    z = torch.randn(3, 5, dtype=torch.float64, requires_grad=True)
    assert set(flow.state_dict()) == {name for name, _ in flow.named_parameters()}
    # pieces of about 70 columns whatever the thread count (16 activations a column)
    monkeypatch.setattr(so3_flow, "PIECE_ELEMENTS", 16 * 70 // torch.get_num_threads())
    shared, own = haar_rotations(30, seed=31), haar_rotations(3 * 30, seed=32).reshape(3, 30, 3, 3)
    for R in (shared, own):  # 30 per image: a piece of 2 images, then one of 1
        expected = _reference_log_prob(flow, z, R)
        value = flow.log_prob(z, R)
        torch.testing.assert_close(value, expected, rtol=0, atol=1e-10)
        if R is shared:  # (matrix_exp's backward in float64 costs 0.1 s a call)
            grads = torch.autograd.grad(value.sum(), [z, *flow.parameters()])
            expected_grads = torch.autograd.grad(expected.sum(), [z, *flow.parameters()])
            for got, want in zip(grads, expected_grads, strict=True):
                torch.testing.assert_close(got, want, rtol=1e-9, atol=1e-9)
        with torch.no_grad():
            torch.testing.assert_close(flow.log_prob(z, R), expected.detach(), rtol=0, atol=1e-10)
    R0 = haar_rotations(3 * 100, seed=33).reshape(3, 100, 3, 3)  # 100 per image: parts of an image
    with torch.no_grad():
        expected = _reference_transform(flow, z, R0)
        T, log_det = flow.transform(z, R0)
    torch.testing.assert_close(T, expected[0], rtol=0, atol=1e-10)
    torch.testing.assert_close(log_det, expected[1], rtol=0, atol=1e-10)
    T, log_det = flow.transform(z, R0[:, :5])  # with autograd
    torch.testing.assert_close(T.detach(), expected[0][:, :5], rtol=0, atol=1e-10)
    torch.testing.assert_close(log_det.detach(), expected[1][:, :5], rtol=0, atol=1e-10)
    # a sweep of 25 rotations a call: the grid's 72 = 2 x 25 + 22, so the last call is a shorter one
    dist = FlowDistribution(z.detach(), flow.log_prob, flow.sample, width=13981)
    assert dist.points_per_call == 25
    with torch.no_grad():
        swept = dist.grid_log_density(0)
        expected = _reference_log_prob(flow, z.detach(), so3_healpix_grid(0, dtype=torch.float64))
    torch.testing.assert_close(swept, expected, rtol=0, atol=1e-10)


def test_flow_without_gradients_gives_the_values_of_the_autograd_path_and_keeps_no_alias():
    """Quick. Without autograd the flow writes its products and activations into buffers kept between calls
    (the grid sweep's path); its values equal the autograd path's, and a later call with other rotations or
    another shape leaves earlier results as they were."""
    flow, z = _random_flow(0.3, seed=4, blocks=2)
    inputs = [haar_rotations(7, seed=1), haar_rotations(7, seed=2), haar_rotations(4, seed=3)]
    with torch.no_grad():
        kept = [flow.log_prob(z, R) for R in inputs]  # the second call reuses the first's buffers
        moved = [flow.transform(z, R.expand(3, -1, -1, -1)) for R in inputs]
    for R, value, (T, log_det) in zip(inputs, kept, moved, strict=True):
        torch.testing.assert_close(value, flow.log_prob(z, R).detach(), rtol=0, atol=1e-10)
        T_ref, log_det_ref = flow.transform(z, R.expand(3, -1, -1, -1))
        torch.testing.assert_close(T, T_ref.detach(), rtol=0, atol=1e-10)
        torch.testing.assert_close(log_det, log_det_ref.detach(), rtol=0, atol=1e-10)
    assert not torch.equal(kept[0], kept[1])  # different rotations, different results, both kept
    with torch.no_grad():  # no rotations: no values
        assert flow.log_prob(z, inputs[0][:0]).shape == (3, 0)
    # a shape first seen in the test loop's inference mode, then a prediction under no_grad, then again
    R = haar_rotations(10, seed=12)
    reference = flow.log_prob(z, R).detach()
    with torch.inference_mode():
        tested = flow.log_prob(z, R)
    with torch.no_grad():
        predicted = flow.log_prob(z, R)
    with torch.inference_mode():
        again = flow.log_prob(z, R)
    for value in (tested, predicted, again):
        torch.testing.assert_close(value, reference, rtol=0, atol=1e-10)


def test_flow_evaluated_by_two_threads_at_once_gives_each_its_own_values():
    """Quick. The buffers of the no-autograd path are per thread: two threads evaluating one model at once
    (a server's request handlers) get the values each would get alone."""
    import threading

    flow, z = _random_flow(0.3, seed=5, blocks=2)
    inputs = [haar_rotations(2000, seed=seed) for seed in (21, 22)]
    with torch.no_grad():
        alone = [flow.log_prob(z, R) for R in inputs]
    results: dict[int, list[torch.Tensor]] = {0: [], 1: []}

    def work(i: int) -> None:
        with torch.no_grad():
            for _ in range(15):
                results[i].append(flow.log_prob(z, inputs[i]))

    threads = [threading.Thread(target=work, args=(i,)) for i in (0, 1)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for i in (0, 1):
        assert len(results[i]) == 15
        for value in results[i]:
            torch.testing.assert_close(value, alone[i], rtol=0, atol=0)


def test_every_sweep_of_a_level_reads_the_same_chunks_so_a_test_batch_runs_the_network_once_per_point():
    """Quick. The test's HDR sweep (groups of fibres) and the spread's full-grid log densities used to cut
    the grid into different chunks wherever the fibre groups do not divide the chunk (level 4: 768 points
    per group), so an implicit family ran its network over the grid twice per test batch."""
    from image2sphere.distributions.grid_protocol import CHUNK_POINTS
    from image2sphere.distributions.hdr_masses import HdrMassAccumulator
    from image2sphere.distributions.implicit import ImplicitDistribution
    from image2sphere.so3.grid import so3_grid_size

    level = 4
    n = math.prod(so3_grid_size(level))
    assert CHUNK_POINTS % (HdrMassAccumulator.GROUP_PIXELS * so3_grid_size(level)[1]) != 0  # the hard case
    scored = []

    def score(features, rotations):
        scored.append(rotations.shape[-3])
        return features[:, :1] * rotations.flatten(-2)[..., 0]  # [B, K]

    dist = ImplicitDistribution(torch.randn(2, 3), score, width=4)
    targets = haar_rotations(2, dtype=torch.float32)[:, None]  # [B, 1, 3, 3]
    with torch.no_grad():
        summary = dist.grid_summary(level, targets)  # log normaliser, mode and HDR masses in one sweep
        log_p = dist.log_prob_grid(level)  # what the spread reads
    assert n <= sum(scored) <= n + 2  # every grid point scored once (and the 2 queries' nearest points)
    torch.testing.assert_close(torch.logsumexp(log_p, dim=1), torch.zeros(2), atol=1e-5, rtol=0)
    torch.testing.assert_close(summary.log_normalizer, torch.logsumexp(dist.grid_log_density(level), dim=1))


def test_implicit_calls_are_cache_sized_on_a_cpu_and_large_elsewhere():
    """Quick. On a CPU the scoring network runs on activations of at most ``CPU_ACTIVATION_ELEMENTS``
    (cache-sized: 2.3x faster for IPDF's level-3 sweep); on another device (here ``meta``, as a GPU) each
    call is a launch of every layer's kernels, so the calls stay as large as the memory budget allows."""
    from image2sphere.distributions import implicit

    def score(features, rotations):
        return features[:, :1] * rotations.flatten(-2)[..., 0]

    cpu = implicit.ImplicitDistribution(torch.randn(16, 3), score, width=64)
    other = implicit.ImplicitDistribution(torch.randn(16, 3, device="meta"), score, width=64)
    assert cpu.points_per_call == implicit.CPU_ACTIVATION_ELEMENTS // (16 * 64) == 1024
    assert other.points_per_call == implicit.MAX_ACTIVATION_ELEMENTS // (16 * 64) == 16384


def test_implicit_density_runs_the_network_once_per_query_without_gradients():
    """Repeated sweeps of one distribution without gradients (the test's log normaliser, the tempered
    distribution's, the spread) evaluate the network once per grid chunk; a query written in place, a
    different query and any evaluation with gradients run it again."""
    from image2sphere.distributions.implicit import ImplicitDistribution

    calls = []

    def score(features, rotations):
        calls.append(rotations.shape[-3])
        return (features[:, :1] * rotations.flatten(-2)[..., 0]).expand(len(features), -1)  # [B, K]

    dist = ImplicitDistribution(torch.randn(2, 3), score, width=4)
    with torch.no_grad():
        first = dist.grid_logsumexp_and_max(2)[0]
        n = len(calls)
        torch.testing.assert_close(
            dist.tempered(0.5).grid_logsumexp_and_max(2)[0], dist.tempered(0.5).grid_logsumexp_and_max(2)[0]
        )
        assert len(calls) == n  # the tempered sweeps read the kept values
        torch.testing.assert_close(dist.grid_logsumexp_and_max(2)[0], first)
        R = haar_rotations(5, dtype=torch.float32)
        before = dist.unnormalized_log_density(R)
        R[0] = R[1]  # written in place: its values are recomputed
        after = dist.unnormalized_log_density(R)
        assert len(calls) == n + 2
        torch.testing.assert_close(after[:, 0], before[:, 1])
    dist.unnormalized_log_density(R)
    assert len(calls) == n + 3  # with gradients: never from the kept values


@pytest.mark.parametrize("group, vanishes", [("T", True), ("O", True), ("I", True), ("C4", False), ("D2", True)])
def test_flow_starts_where_the_expected_gradient_of_a_symmetric_label_vanishes_unless_an_axis_is_invariant(
    group, vanishes
):
    """At its start (every layer the identity) each layer's first-order change of the log density is a
    degree-1 function of the rotation (a Möbius centre moves one column; the affine layer changes q q^T).
    Averaged over a symmetry group with no invariant axis (tetrahedron, cube, icosahedron, a dihedral
    group), degree 1 averages to zero: the expected gradient of the loss with a random equivalent label
    (and the gradient of the set-averaged loss) is exactly zero, and only the noise of the random
    labels moves the flow off the uniform distribution. A group that keeps an axis (a cone's, here C4)
    has a gradient at the start (docs/methods.md, "Successors at small scale")."""
    z = torch.randn(1, 5, dtype=torch.float64)
    R = haar_rotations(1, seed=9)[0]
    S = rotation_group(group).to(torch.float64)
    for start in ("identity", "random"):
        torch.manual_seed(4)
        flow = SO3Flow(5, blocks=2, hidden=16, start=start).double()
        (-flow.log_prob(z, (R @ S)[None]).mean()).backward()
        norm = math.sqrt(sum(p.grad.square().sum().item() for p in flow.parameters() if p.grad is not None))
        if start == "identity":
            assert (norm < 1e-10) if vanishes else (norm > 1e-2), norm
        else:  # the authors' random start is off the saddle for every group
            assert norm > 1e-2, norm


def test_flow_random_start_is_a_normalised_non_uniform_density_and_start_is_checked():
    """``start="random"`` (PyTorch's default initialisation of every layer, as the authors' code) is a
    proper density far from uniform at the start: the level-3 grid mean of ``p * pi^2`` is 1 to 1e-2, and
    its log density spreads over more than 1 nat. Any other ``start`` is refused, naming the key."""
    torch.manual_seed(5)
    flow = SO3Flow(5, blocks=2, hidden=16, start="random").double()
    z = torch.randn(2, 5, dtype=torch.float64)
    with torch.no_grad():
        log_p = flow.log_prob(z, so3_healpix_grid(3, dtype=torch.float64))  # [2, 36864]
    torch.testing.assert_close(log_p.exp().mean(1) * math.pi**2, torch.ones(2, dtype=torch.float64), atol=1e-2, rtol=0)
    assert (log_p.max(1).values - log_p.min(1).values > 1).all()
    with pytest.raises(ValueError, match="start must be 'identity' or 'random'"):
        SO3Flow(5, start="uniform")
    with pytest.raises(ValueError, match="model.net.start must be"):
        RotationFlow(TinyEncoder(), image_size=16, condition_dim=6, blocks=1, hidden=8, start="zeros")
