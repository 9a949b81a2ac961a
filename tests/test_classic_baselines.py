"""The older baselines of the I2S paper's tables: viewpoint classification (Tulsiani & Malik 2015),
spherical regression (Liao et al. 2019) and Bin & Delta (Mahendran et al. 2018).

References are independent of the code under test: scipy's Euler angles, quaternions and rotation
vectors, Haar-random rotations, brute-force nearest grid points, analytic volumes, cross-entropies
written out with torch.nn.functional.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
import torch.nn.functional as F
from scipy.spatial.transform import Rotation

from conftest import REPO, brute_force_nearest, haar_rotations
from image2sphere.distributions.euler_bins import (
    EulerBins,
    elevation_bin_log_volumes,
    euler_bin_index,
    euler_bins_nll,
)
from image2sphere.nn import BinDeltaRegression, ResNetEncoder, SphericalRegression, ViewpointBinsNet
from image2sphere.nn.classification_regression import QUATERNION_SIGNS, quaternion_sign_class
from image2sphere.nn.regression import PerClassLinear
from image2sphere.so3 import (
    aet_to_matrix,
    geodesic_distance,
    matrix_to_aet_biternions,
    matrix_to_quaternion,
    so3_healpix_grid,
)

D = torch.float64
PI2 = math.pi**2
N_BINS = 21


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    yield


def scipy_euler_bins(R: torch.Tensor, n: int) -> np.ndarray:
    """Bins of (azimuth, elevation, tilt) from scipy: ``R = Rx(-t) Ry(-e) Rz(-a)`` is scipy's intrinsic
    ``"XYZ"`` sequence with angles ``(-t, -e, -a)`` (middle angle in [-pi/2, pi/2])."""
    xyz = Rotation.from_matrix(R.numpy()).as_euler("XYZ")  # [..., 3]
    t, e, a = -xyz[:, 0], -xyz[:, 1], -xyz[:, 2]
    frac = np.stack([np.mod(a, 2 * np.pi) / (2 * np.pi), e / np.pi + 0.5, np.mod(t, 2 * np.pi) / (2 * np.pi)], 1)
    return np.clip(np.floor(frac * n).astype(int), 0, n - 1)


def random_logits(batch: int, scale: float, seed: int) -> torch.Tensor:
    return scale * torch.randn(batch, 3, N_BINS, dtype=D, generator=torch.Generator().manual_seed(seed))


# ================================================================================== viewpoint bins
def test_bin_index_matches_scipy_euler_angles():
    R = haar_rotations(2000, seed=1)
    ours = euler_bin_index(R, N_BINS).numpy()
    ref = scipy_euler_bins(R, N_BINS)
    assert (ours == ref).mean() > 0.999  # a rotation within rounding of a bin edge may differ
    assert ((ours == ref).all(1) | (np.abs(ours - ref) <= 1).all(1)).all()


def test_box_volumes_are_the_haar_measure():
    log_v = elevation_bin_log_volumes(N_BINS)
    # analytic: the boxes fill SO(3), whose volume is pi^2
    assert (N_BINS**2 * log_v.exp().sum()).item() == pytest.approx(PI2, rel=1e-12)
    # independent: the fraction of Haar-random rotations in each elevation bin is its volume share
    n = 100_000
    index = euler_bin_index(haar_rotations(n, seed=2), N_BINS)[:, 1]
    freq = torch.bincount(index, minlength=N_BINS).to(D) / n
    share = N_BINS**2 * log_v.exp() / PI2
    std = torch.sqrt(share * (1 - share) / n)
    assert ((freq - share).abs() / std).max() < 5
    assert share[0] < share[N_BINS // 2] / 10  # the polar bins are small (cos e)


@pytest.mark.parametrize("scale", [0.0, 1.0, 5.0, 30.0])
def test_density_integrates_to_one(scale):
    """Midpoint rule in the Euler chart with the Haar measure ``cos e da de dt / 8`` written out (4
    sub-cells per bin, so no node lies on a box edge): exact up to the rule's error on ``cos e``."""
    dist = EulerBins(random_logits(2, scale, seed=3))
    m = 4 * N_BINS
    mid = (torch.arange(m, dtype=D) + 0.5) / m
    a, e, t = torch.meshgrid(2 * math.pi * mid, math.pi * (mid - 0.5), 2 * math.pi * mid, indexing="ij")
    weights = (e.cos() * (2 * math.pi / m) ** 2 * (math.pi / m) / 8).reshape(-1)  # Haar volume of each cell
    nodes = aet_to_matrix(a, e, t).reshape(-1, 3, 3)
    total = sum(
        (dist.exact_log_density(nodes[i : i + 65536]).exp() * weights[i : i + 65536]).sum(1)
        for i in range(0, len(nodes), 65536)
    )
    torch.testing.assert_close(total, torch.ones(2, dtype=D), atol=1e-3, rtol=0)
    torch.testing.assert_close(dist.exact_log_normalizer(), torch.zeros(2, dtype=D))


@pytest.mark.parametrize("scale", [0.0, 1.0])
def test_broad_density_integrates_to_one_on_the_healpix_grid(scale):
    """An equal-volume grid that knows nothing of the chart (a box density is summed exactly up to
    the grid cells its edges cut: ~1e-2 at level 4 for broad parameters)."""
    dist = EulerBins(random_logits(2, scale, seed=3))
    G = so3_healpix_grid(4, dtype=D).reshape(-1, 3, 3)
    total = sum(dist.exact_log_density(G[i : i + 65536]).exp().sum(1) for i in range(0, len(G), 65536))
    torch.testing.assert_close(total * PI2 / len(G), torch.ones(2, dtype=D), atol=0.03, rtol=0)
    torch.testing.assert_close(dist.log_prob_grid(2).exp().sum(1), torch.ones(2, dtype=D))


def test_density_is_the_box_probability_over_its_volume():
    logits = random_logits(1, 2.0, seed=4)
    dist = EulerBins(logits)
    R = haar_rotations(50, seed=5)
    bins = torch.as_tensor(scipy_euler_bins(R, N_BINS))  # [50, 3]
    log_p = torch.log_softmax(logits[0], dim=-1)  # [3, n]
    expected = log_p[0, bins[:, 0]] + log_p[1, bins[:, 1]] + log_p[2, bins[:, 2]]
    expected = expected - elevation_bin_log_volumes(N_BINS)[bins[:, 1]]
    torch.testing.assert_close(dist.exact_log_density(R)[0], expected)


def test_mode_is_the_densest_box_centre():
    logits = torch.zeros(1, 3, N_BINS, dtype=D)
    logits[0, 0, 5] = logits[0, 2, 17] = 3.0
    # two elevation bins equally likely: the polar one is smaller, so its density is higher
    logits[0, 1, 0] = logits[0, 1, 10] = 3.0
    dist = EulerBins(logits)
    mode = dist.exact_mode()
    assert euler_bin_index(mode, N_BINS).tolist() == [[5, 0, 17]]
    at_mode = dist.exact_log_density(mode[:, None])[0, 0]
    G = so3_healpix_grid(3, dtype=D).reshape(-1, 3, 3)
    assert (dist.exact_log_density(G) <= at_mode + 1e-12).all()
    # the mode is the centre of the box: half way in azimuth and tilt, half way in sin(elevation)
    a, e, t = (torch.atan2(x[..., 1], x[..., 0]) for x in matrix_to_aet_biternions(mode))
    width = 2 * math.pi / N_BINS
    assert a.item() % (2 * math.pi) == pytest.approx(5.5 * width)
    assert t.item() % (2 * math.pi) == pytest.approx(17.5 * width)
    lo, hi = -math.pi / 2, -math.pi / 2 + math.pi / N_BINS
    assert math.sin(e.item()) == pytest.approx((math.sin(lo) + math.sin(hi)) / 2)
    # the grid protocol's argmax lands in the same box
    assert euler_bin_index(dist.mode(4), N_BINS).tolist() == [[5, 0, 17]]


def test_sampling_follows_the_bins_and_is_haar_uniform_inside_a_box():
    logits = random_logits(1, 1.5, seed=6)
    dist = EulerBins(logits)
    n = 40_000
    samples = dist.exact_sample(n, generator=torch.Generator().manual_seed(7))
    assert samples.shape == (1, n, 3, 3)
    torch.testing.assert_close(samples[0].transpose(-1, -2) @ samples[0], torch.eye(3, dtype=D).expand(n, 3, 3))
    index = torch.as_tensor(scipy_euler_bins(samples[0], N_BINS))  # [n, 3]
    probs = torch.softmax(logits[0], dim=-1)  # [3, n_bins]
    for angle in range(3):
        freq = torch.bincount(index[:, angle], minlength=N_BINS).to(D) / n
        std = torch.sqrt(probs[angle] * (1 - probs[angle]) / n) + 1e-4
        assert ((freq - probs[angle]).abs() / std).max() < 5, angle
    # inside the polar elevation bin the Haar measure is cos(e) de: sin(e) is uniform, e is not
    polar = torch.zeros(1, 3, N_BINS, dtype=D)
    polar[0, 1, N_BINS - 1] = 50.0
    draws = EulerBins(polar).exact_sample(20_000, generator=torch.Generator().manual_seed(8))[0]
    sin_e = -draws[:, 0, 2]  # R02 = -sin e
    lo = math.sin(math.pi / 2 - math.pi / N_BINS)
    assert (sin_e >= lo - 1e-9).all()
    assert sin_e.mean().item() == pytest.approx((lo + 1) / 2, abs=4 * (1 - lo) / math.sqrt(12 * 20_000))


def test_loss_is_the_three_cross_entropies_plus_the_box_volume():
    output = torch.randn(6, 3 * N_BINS, dtype=D, generator=torch.Generator().manual_seed(9), requires_grad=True)
    R = haar_rotations(6, seed=10)
    bins = torch.as_tensor(scipy_euler_bins(R, N_BINS))
    logits = output.reshape(6, 3, N_BINS)
    ce = sum(F.cross_entropy(logits[:, i], bins[:, i], reduction="none") for i in range(3))
    loss = euler_bins_nll(output, R, N_BINS)
    torch.testing.assert_close(loss, ce + elevation_bin_log_volumes(N_BINS)[bins[:, 1]])
    loss.sum().backward()
    assert torch.isfinite(output.grad).all() and output.grad.abs().sum() > 0


def test_euler_bins_bad_input():
    with pytest.raises(ValueError, match=r"shape \(B, 3, num_bins\)"):
        EulerBins(torch.zeros(2, 4, N_BINS))
    with pytest.raises(ValueError, match="finite"):
        EulerBins(torch.full((1, 3, N_BINS), float("nan")))
    with pytest.raises(ValueError, match=r"shape \(B, 63\)"):
        EulerBins.from_output(torch.zeros(2, 60), N_BINS)
    with pytest.raises(ValueError, match="num_bins"):
        ViewpointBinsNet(ResNetEncoder(depth=18, weights=None), 32, num_bins=0)
    with pytest.raises(ValueError, match="orthonormal|rotation"):
        euler_bins_nll(torch.zeros(1, 3 * N_BINS), 2 * torch.eye(3)[None], N_BINS)


# ================================================================================== spherical regression
def test_matrix_to_quaternion_matches_scipy_with_w_non_negative():
    R = torch.cat([haar_rotations(500, seed=11), torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=D))[None]])
    q = matrix_to_quaternion(R, "wxyz")
    ref = torch.as_tensor(Rotation.from_matrix(R.numpy()).as_quat()[:, [3, 0, 1, 2]])  # xyzw -> wxyz
    ref = torch.where(ref[:, :1] < 0, -ref, ref)
    assert (q[:, 0] >= 0).all()
    # a 180 degree turn (w = 0) has two valid signs; every other quaternion is unique
    torch.testing.assert_close(q[:-1], ref[:-1])
    torch.testing.assert_close(q[-1].abs(), torch.tensor([0.0, 1.0, 0.0, 0.0], dtype=D))


def test_sign_classes_cover_the_eight_patterns():
    q = matrix_to_quaternion(haar_rotations(400, seed=12), "wxyz")
    c = quaternion_sign_class(q)
    assert sorted(c.unique().tolist()) == list(range(8))
    torch.testing.assert_close(QUATERNION_SIGNS.to(D)[c] * q.abs(), q)


def test_spherical_regression_perfect_output_has_zero_loss_and_predicts_the_rotation():
    net = SphericalRegression(ResNetEncoder(depth=18, weights=None), 32, hidden=16).double()
    R = haar_rotations(8, seed=13)
    q = matrix_to_quaternion(R, "wxyz")
    signs = F.one_hot(quaternion_sign_class(q), 8).to(D)
    output = torch.cat([torch.log(q.pow(2).clamp_min(1e-300)), 40 * signs], dim=1).requires_grad_()
    predicted = net.output_distribution(output).mode()
    assert geodesic_distance(predicted, R).max() < 1e-6
    loss = net.loss(output, R, 3)
    assert loss.max() < 1e-6
    loss.sum().backward()
    assert torch.isfinite(output.grad).all()
    # a wrong sign class costs its cross-entropy; a wrong |q| its weighted cosine distance
    wrong = output.detach().clone()
    wrong[:, 4:] = 40 * torch.roll(signs, 1, dims=1)
    torch.testing.assert_close(net.loss(wrong, R, 3), torch.full((8,), 40.0, dtype=D), atol=1e-6, rtol=0)
    flat = output.detach().clone()
    flat[:, :4] = 0  # |q| = (1/2, 1/2, 1/2, 1/2)
    torch.testing.assert_close(net.loss(flat, R, 3), 10 * (1 - q.abs().sum(1) / 2), atol=1e-9, rtol=0)


def test_per_class_last_layer_is_each_class_own_layer():
    torch.manual_seed(0)
    layer = PerClassLinear(5, 4, num_classes=3).double()
    x = torch.randn(6, 5, dtype=D)
    classes = torch.tensor([0, 1, 2, 2, 1, 0])
    y = layer(x, F.one_hot(classes, 3))
    for i, c in enumerate(classes.tolist()):
        expected = x[i] @ layer.weight[4 * c : 4 * c + 4].T + layer.bias[4 * c : 4 * c + 4]
        torch.testing.assert_close(y[i], expected)
    net = SphericalRegression(ResNetEncoder(depth=18, weights=None), 32, hidden=8, num_classes=3)
    with pytest.raises(ValueError, match="class_index"):
        net(torch.randn(2, 3, 32, 32))
    assert net(torch.randn(2, 3, 32, 32), torch.tensor([0, 2])).shape == (2, 12)


# ================================================================================== Bin & Delta
def test_bin_delta_bins_are_the_grid_and_labels_the_nearest_bin():
    net = BinDeltaRegression(ResNetEncoder(depth=18, weights=None), 32, hidden=16).double()
    assert net.num_bins == 72
    torch.testing.assert_close(net.centres.double(), so3_healpix_grid(0, dtype=D).reshape(-1, 3, 3).float().double())
    R = haar_rotations(30, seed=14)
    true_bin = brute_force_nearest(R, so3_healpix_grid(0, dtype=D).reshape(-1, 3, 3))
    # perfect output: the true bin, and its centre corrected onto R
    delta = torch.zeros(30, 72, 3, dtype=D)
    correction = net.centres.double()[true_bin].transpose(-1, -2) @ R
    delta[torch.arange(30), true_bin] = torch.as_tensor(Rotation.from_matrix(correction.numpy()).as_rotvec())
    logits = 40 * F.one_hot(true_bin, 72).to(D)
    output = torch.cat([logits, delta.reshape(30, -1)], dim=1).requires_grad_()
    # (the centres are stored in float32: orthonormal to ~1e-7, which the arccos of the geodesic
    # distance turns into ~1e-4 rad)
    torch.testing.assert_close(net.output_distribution(output).mode(), R, atol=1e-6, rtol=0)
    loss = net.loss(output, R, 3)
    assert loss.max() < 1e-3
    loss.sum().backward()
    assert torch.isfinite(output.grad).all()
    # no correction: the loss is the geodesic distance to the bin centre (and at most ~ the bin radius)
    plain = torch.cat([logits, torch.zeros(30, 216, dtype=D)], dim=1)
    torch.testing.assert_close(
        net.loss(plain, R, 3), geodesic_distance(net.centres.double()[true_bin], R), atol=1e-6, rtol=0
    )
    # the prediction uses the most likely bin's correction, not the true bin's
    other = (true_bin + 1) % 72
    swapped = torch.cat([40 * F.one_hot(other, 72).to(D), delta.reshape(30, -1)], dim=1)
    torch.testing.assert_close(net.output_distribution(swapped).mode(), net.centres.double()[other])


def test_bin_delta_bad_input():
    encoder = ResNetEncoder(depth=18, weights=None)
    with pytest.raises(ValueError, match="bin_level=3 is too fine"):
        BinDeltaRegression(encoder, 32, bin_level=3)
    with pytest.raises(ValueError, match="delta_weight"):
        BinDeltaRegression(encoder, 32, delta_weight=-1.0)
    with pytest.raises(ValueError, match="abs_weight"):
        SphericalRegression(encoder, 32, abs_weight=float("nan"))
    net = BinDeltaRegression(encoder, 32, hidden=8)
    with pytest.raises(ValueError, match=r"shape \(B, 288\)"):
        net.output_distribution(torch.zeros(2, 100))


def test_the_old_name_of_the_viewpoint_bins_network_still_resolves():
    """Checkpoints store ``model.net._target_``; those written before the rename name EulerBinsNet, which
    must still build the same class (conf/model/viewpoint_bins.yaml now names ViewpointBinsNet)."""
    from hydra.utils import get_class
    from omegaconf import OmegaConf

    assert get_class("image2sphere.nn.EulerBinsNet") is ViewpointBinsNet
    stored = OmegaConf.load(REPO / "conf" / "model" / "viewpoint_bins.yaml")
    assert stored.net._target_ == "image2sphere.nn.ViewpointBinsNet"
