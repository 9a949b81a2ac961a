"""I2S over the icosahedral group (nn/icosahedral.py): the group, the point set, exact equivariance of
every layer and of the predicted rotation, the anchor-regression loss and the generic interface.

The references here recompute group products and point images from the matrices (nearest match),
independently of the Cayley table and the action table the layers use.
"""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation

from image2sphere.distributions.base import PointEstimate, PoseDistribution
from image2sphere.nn import ResNetEncoder, SpatialS2Projector
from image2sphere.nn.base import method_of
from image2sphere.nn.icosahedral import (
    IcosahedralGroupConv,
    IcosahedralI2S,
    IcosahedralLifting,
    PointSetProjector,
    icosahedral_group,
    icosahedral_points,
    point_action,
    rotate_point_signal,
    translate_group_signal,
)
from image2sphere.so3.grid import s2_healpix_grid
from image2sphere.so3.rotations import geodesic_distance, random_rotations

TOL = 1e-10
G = icosahedral_group()


def _angle_deg(R: torch.Tensor) -> torch.Tensor:
    return torch.rad2deg(torch.acos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1)))


def _nearest(targets: torch.Tensor, queries: torch.Tensor) -> torch.Tensor:
    """Index of the target nearest each query (flattened entries), asserting an exact match."""
    diff = (queries.flatten(1)[:, None] - targets.flatten(1)[None]).abs().amax(-1)  # [N, M]
    best, index = diff.min(dim=1)
    assert best.max() < 1e-9
    return index


def _small_net(num_classes: int = 0, **kwargs) -> IcosahedralI2S:
    torch.manual_seed(0)
    encoder = ResNetEncoder(depth=18, weights=None)
    return IcosahedralI2S(encoder, 32, sphere_channels=8, group_channels=4, num_classes=num_classes, **kwargs)


# ------------------------------------------------------------------------------------------ the group
def test_group_is_60_distinct_rotations_with_an_exact_cayley_table():
    M = G.matrices
    assert M.shape == (60, 3, 3) and M.dtype == torch.float64
    torch.testing.assert_close(M.transpose(1, 2) @ M, torch.eye(3, dtype=M.dtype).expand(60, 3, 3), atol=1e-12, rtol=0)
    torch.testing.assert_close(torch.linalg.det(M), torch.ones(60, dtype=M.dtype), atol=1e-12, rtol=0)
    assert torch.equal(M[0], torch.eye(3, dtype=M.dtype))
    distance = (M[:, None] - M[None]).flatten(2).norm(dim=-1) + 10 * torch.eye(60, dtype=M.dtype)
    assert distance.min() > 0.5  # distinct: the nearest two differ by a 72-degree turn
    # the same set as scipy's, and the rotation angles of I: 1 x 0, 24 x 72/144, 20 x 120, 15 x 180 degrees
    _nearest(M, torch.as_tensor(Rotation.create_group("I").as_matrix()))
    angles = _angle_deg(M).round().long().tolist()
    assert sorted(set(angles)) == [0, 72, 120, 144, 180]
    assert [angles.count(a) for a in (0, 72, 120, 144, 180)] == [1, 12, 20, 12, 15]
    # closed under products, and the Cayley table is the products (recomputed by matching here)
    products = (M[:, None] @ M[None]).reshape(-1, 3, 3)
    assert torch.equal(G.cayley.flatten(), _nearest(M, products))
    torch.testing.assert_close(M[G.cayley], M[:, None] @ M[None], atol=1e-12, rtol=0)
    for row in (*G.cayley, *G.cayley.T):  # a Latin square
        assert sorted(row.tolist()) == list(range(60))
    torch.testing.assert_close(M[G.inverse], M.transpose(1, 2), atol=1e-12, rtol=0)
    assert torch.equal(G.cayley[torch.arange(60), G.inverse], torch.zeros(60, dtype=torch.long))
    # associativity of the table: (ab)c = a(bc)
    a, b, c = torch.meshgrid(torch.arange(60), torch.arange(0, 60, 7), torch.arange(0, 60, 11), indexing="ij")
    assert torch.equal(G.cayley[G.cayley[a, b], c], G.cayley[a, G.cayley[b, c]])


@pytest.mark.parametrize("n_orbits", [0, 1, 2, 3])
def test_point_set_is_closed_and_the_action_is_a_homomorphism(n_orbits):
    P = icosahedral_points(n_orbits)
    assert P.shape == (62 + 60 * n_orbits, 3) and P.dtype == torch.float64
    torch.testing.assert_close(P.norm(dim=1), torch.ones(len(P), dtype=P.dtype), atol=1e-12, rtol=0)
    gaps = torch.cdist(P, P) + 10 * torch.eye(len(P), dtype=P.dtype)
    assert gaps.min() > 0.05  # distinct points (at least ~3 degrees apart)
    action = point_action(P)
    assert action.shape == (60, len(P))
    for row in action:  # each group element permutes the points
        assert sorted(row.tolist()) == list(range(len(P)))
    moved = torch.einsum("gij,pj->gpi", G.matrices, P)  # [60, n, 3]
    torch.testing.assert_close(P[action], moved, atol=1e-12, rtol=0)
    assert torch.equal(action[0], torch.arange(len(P)))
    # (ab) p = a (b p) for every pair
    assert torch.equal(action[G.cayley], action[:, None].expand(-1, 60, -1).gather(2, action[None].expand(60, -1, -1)))
    # stabilisers: 5-, 3- and 2-fold axes are fixed by 5, 3 and 2 elements; the generic orbits by the identity only
    fixed = (action == torch.arange(len(P))).sum(0)
    assert fixed.tolist() == [5] * 12 + [3] * 20 + [2] * 30 + [1] * (60 * n_orbits)


def test_point_action_rejects_a_set_not_closed_under_the_group():
    with pytest.raises(AssertionError, match="no exact match"):
        point_action(icosahedral_points(1)[:-1])
    with pytest.raises(ValueError, match=r"shape \(n, 3\), got \(5, 2\)"):
        point_action(torch.zeros(5, 2))
    with pytest.raises(ValueError, match="n_orbits"):
        icosahedral_points(4)


# ------------------------------------------------------------------------------------------ the layers
def test_lifting_is_the_formula_and_exactly_equivariant():
    torch.manual_seed(1)
    P = icosahedral_points(1)
    layer = IcosahedralLifting(3, 5, P).double()
    with torch.no_grad():
        layer.bias.normal_()
    x = torch.randn(2, 3, len(P), dtype=torch.float64)
    f = layer(x)
    assert f.shape == (2, 5, 60)
    # f(g) = sum_p psi(g^-1 p) Phi(p) + b, with g^-1 p found from the matrices
    pulled = _nearest(P, torch.einsum("gji,pj->gpi", G.matrices, P).reshape(-1, 3)).view(60, len(P))  # g^T p
    reference = torch.einsum("bip,oigp->bog", x, layer.weight[:, :, pulled]) + layer.bias[:, None]
    torch.testing.assert_close(f, reference, atol=TOL, rtol=0)
    action = point_action(P)
    for h in range(60):
        torch.testing.assert_close(
            layer(rotate_point_signal(x, h, action)), translate_group_signal(f, h), atol=TOL, rtol=0
        )
    with pytest.raises(ValueError, match=r"got \(2, 4, 122\)"):
        layer(torch.zeros(2, 4, len(P), dtype=torch.float64))


def test_group_conv_is_the_formula_and_exactly_equivariant():
    torch.manual_seed(2)
    layer = IcosahedralGroupConv(4, 3).double()
    f = torch.randn(2, 4, 60, dtype=torch.float64)
    out = layer(f)
    # f'(g) = sum_k psi(k^-1 g) f(k) + b, with k^-1 g found from the matrices
    products = G.matrices.transpose(1, 2)[:, None] @ G.matrices[None]  # [60 (k), 60 (g), 3, 3]: k^-1 g
    k_inv_g = _nearest(G.matrices, products.reshape(-1, 3, 3)).view(60, 60)
    reference = torch.einsum("bik,oikg->bog", f, layer.weight[:, :, k_inv_g]) + layer.bias[:, None]
    torch.testing.assert_close(out, reference, atol=TOL, rtol=0)
    for h in range(60):
        torch.testing.assert_close(
            layer(translate_group_signal(f, h)), translate_group_signal(out, h), atol=TOL, rtol=0
        )
    with pytest.raises(ValueError, match=r"got \(2, 4, 59\)"):
        layer(torch.zeros(2, 4, 59, dtype=torch.float64))


def test_whole_head_and_predicted_rotation_are_exactly_equivariant():
    """An input rotated by ``h`` moves the output to ``f(h^-1 g)``, the argmax anchor to ``h k*`` and the
    prediction to ``h @ R`` (and not to ``R @ h``: the test can tell the sides apart)."""
    net = _small_net(n_group_conv=2).double().eval()
    action = point_action(icosahedral_points(2))
    x = torch.randn(3, 8, action.shape[1], dtype=torch.float64).relu()  # the projector's output is >= 0
    out = net.head(x)
    with torch.no_grad():  # residuals of a visible size, so that a wrong side would show
        out[:, 1:] *= 10
    R = net.output_distribution(out).mode()
    best = out[:, 0].argmax(dim=1)
    for h in range(60):
        moved = net.head(rotate_point_signal(x, h, action))
        torch.testing.assert_close(moved, translate_group_signal(net.head(x), h), atol=TOL, rtol=0)
        with torch.no_grad():
            moved[:, 1:] *= 10
        assert torch.equal(moved[:, 0].argmax(dim=1), G.cayley[h, best])
        R_moved = net.output_distribution(moved).mode()
        torch.testing.assert_close(R_moved, G.matrices[h] @ R, atol=TOL, rtol=0)
        if h != 0:
            assert (R_moved - R @ G.matrices[h]).abs().max() > 1e-3


def test_projector_reads_the_map_as_i2s_spatial_projector():
    """On I2S's own HEALPix hemisphere the point-set projector has I2S's interpolation weights, and the
    points on the far side read nothing."""
    alpha, beta = s2_healpix_grid(2, dtype=torch.float64)
    xyz = torch.stack([beta.sin() * alpha.sin(), beta.cos(), beta.sin() * alpha.cos()], dim=1)
    ours = PointSetProjector(6, 7, xyz, sphere_channels=4)
    theirs = SpatialS2Projector(6, 7, sphere_channels=4, level=2)
    front = beta < math.pi / 2 - 1e-9
    assert torch.equal(ours.visible, torch.nonzero(front).flatten())
    torch.testing.assert_close(ours.interpolation, theirs.interpolation[..., front[: len(theirs.beta)]])
    with torch.no_grad():
        ours.conv.load_state_dict(theirs.conv.state_dict())
    features = torch.randn(2, 6, 7, 7)
    signal = ours(features)
    assert signal.shape == (2, 4, len(xyz))
    assert (signal[..., ~front] == 0).all()
    torch.testing.assert_close(signal[..., front], theirs.project(features)[..., front[: len(theirs.beta)]])
    with pytest.raises(ValueError, match=r"got \(2, 6, 5, 5\)"):
        ours(torch.randn(2, 6, 5, 5))


# ------------------------------------------------------------------------------------------ loss and interface
def test_nearest_anchor_is_the_geodesic_nearest():
    net = _small_net()
    rotations = random_rotations(50, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    distances = geodesic_distance(G.matrices[None], rotations[:, None])  # [50, 60]
    assert torch.equal(net.nearest_anchor(rotations), distances.argmin(dim=1))
    assert torch.equal(net.nearest_anchor(G.matrices), torch.arange(60))


@pytest.mark.parametrize("rotation_loss", ["geodesic", "frobenius"])
def test_loss_is_finite_with_finite_gradients_on_an_anchor(rotation_loss):
    net = _small_net(rotation_loss=rotation_loss).double()
    # an output whose residuals are exactly zero and labels exactly on anchors: the distance is 0, where a
    # plain acos would have an infinite derivative
    output = torch.zeros(2, 4, 60, dtype=torch.float64, requires_grad=True)
    labels = G.matrices[[7, 42]].clone()
    loss = net.loss(output, labels, 3)
    torch.testing.assert_close(loss, torch.full((2,), math.log(60), dtype=torch.float64))  # the uniform CE only
    loss.sum().backward()
    assert torch.isfinite(output.grad).all()
    # through the network, labels on anchors and off them
    images = torch.randn(4, 3, 32, 32, dtype=torch.float64)
    labels = torch.cat([G.matrices[[0, 13]], random_rotations(2, generator=torch.Generator().manual_seed(4))])
    loss = net.loss(net(images), labels, 3)
    assert loss.shape == (4,) and torch.isfinite(loss).all()
    loss.sum().backward()
    grads = [p.grad for p in net.parameters() if p.requires_grad]
    assert all(g is not None and torch.isfinite(g).all() for g in grads)
    assert net.projector.interpolation.grad.abs().sum() > 0 and net.lifting.weight.grad.abs().sum() > 0


def test_a_few_steps_on_a_fixed_batch_lower_the_loss():
    net = _small_net()
    images = torch.randn(4, 3, 32, 32, generator=torch.Generator().manual_seed(5))
    labels = random_rotations(4, generator=torch.Generator().manual_seed(6))
    optimizer = torch.optim.Adam(net.parameters(), lr=3e-3)
    losses = []
    for _ in range(8):
        loss = net.loss(net(images), labels, 3).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(float(loss.detach()))
    assert losses[-1] < 0.75 * losses[0], losses


def test_generic_interface_gives_a_point_estimate_with_a_rotation_mode():
    net = _small_net(num_classes=3).eval()
    images = torch.randn(2, 3, 32, 32)
    with torch.no_grad():
        dist = net.distribution(images, torch.tensor([0, 2]))
        output_distribution, loss = method_of(net)
        output = net(images, torch.tensor([1, 1]))
    assert isinstance(dist, PointEstimate) and isinstance(dist, PoseDistribution) and not dist.has_density
    mode = dist.mode()
    assert mode.shape == (2, 3, 3)
    torch.testing.assert_close(mode.transpose(1, 2) @ mode, torch.eye(3).expand(2, 3, 3), atol=1e-5, rtol=0)
    torch.testing.assert_close(torch.linalg.det(mode), torch.ones(2), atol=1e-5, rtol=0)
    assert output.shape == (2, 4, 60) and output_distribution(output).mode().shape == (2, 3, 3)
    # the class one-hot reaches the output
    assert not torch.allclose(output, net(images, torch.tensor([0, 2])).detach())
    with pytest.raises(ValueError, match="class_index"):
        net(images)
    with pytest.raises(ValueError, match=r"\(B, 4, 60\), got \(2, 240\)"):
        net.output_distribution(output.flatten(1))
    with pytest.raises(ValueError, match="rotation_loss"):
        _small_net(rotation_loss="l1")
    with pytest.raises(ValueError, match="residual_weight"):
        _small_net(residual_weight=-1.0)
