"""The interface every method's output goes through (PoseDistribution), and the regression baselines.

* The generic grid protocol of the base class (chunked sweeps) against the fast paths of the Fourier
  family (SO3Distribution's grid evaluator), which compute the same quantities another way.
* Point estimates: a mode, no density.
* The 6D (Gram-Schmidt) and 9D (special Procrustes) maps and the regression network.
"""

from __future__ import annotations

import math

import pytest
import torch
from scipy.spatial.transform import Rotation as ScipyRotation

import image2sphere.distributions.grid_protocol as grid_protocol
from image2sphere.distributions import DensityNotAvailable, PointEstimate, PoseDistribution, SO3Distribution
from image2sphere.nn.regression import RotationRegression
from image2sphere.so3 import geodesic_distance, project_to_so3, random_rotations, rotation_6d_to_matrix, so3_grid_size
from image2sphere.so3.grid import so3_healpix_index_to_matrix

GENERIC = PoseDistribution  # the base class's methods, called on an SO3Distribution


@pytest.fixture
def fourier() -> SO3Distribution:
    torch.manual_seed(0)
    return SO3Distribution(torch.randn(3, 35, dtype=torch.float64) * 2, lmax=2)


@pytest.mark.parametrize("chunk", [1000, 1 << 16])
def test_generic_grid_sweep_matches_the_fast_path(fourier, chunk, monkeypatch):
    monkeypatch.setattr(grid_protocol, "CHUNK_POINTS", chunk)
    lse, top, arg = GENERIC.grid_logsumexp_and_max(fourier, 3)
    lse_fast, top_fast, arg_fast = fourier.grid_logsumexp_and_max(3)
    torch.testing.assert_close(lse, lse_fast, rtol=0, atol=1e-9)
    torch.testing.assert_close(top, top_fast, rtol=0, atol=1e-9)
    assert torch.equal(arg, arg_fast)
    R = random_rotations(5, dtype=torch.float64)
    torch.testing.assert_close(GENERIC.log_density(fourier, R, 3), fourier.log_density(R, 3), rtol=0, atol=1e-9)
    index = torch.tensor([[0, 5, 36863]] * 3)
    torch.testing.assert_close(
        GENERIC.log_prob_at_index(fourier, index, 3), fourier.log_prob_at_index(index, 3), rtol=0, atol=1e-9
    )
    torch.testing.assert_close(GENERIC.grid_log_density(fourier, 2), fourier.grid_logits(2), rtol=0, atol=1e-9)


def test_generic_points_above_modes_and_threshold_match(fourier):
    for (i, p), (i_fast, p_fast) in zip(
        GENERIC.points_above(fourier, 2e-4, 3), fourier.points_above(2e-4, 3), strict=True
    ):
        assert torch.equal(i, i_fast) and len(i) > 0
        torch.testing.assert_close(p, p_fast, rtol=0, atol=1e-12)
    torch.testing.assert_close(GENERIC.max_prob(fourier, 3), fourier.max_prob(3))
    dense = torch.softmax(fourier.grid_logits(3), dim=-1).amax(-1)  # the largest grid probability, densely
    threshold = torch.clamp(dense * (1 - 1e-6), max=10.0 / math.prod(so3_grid_size(3)))
    torch.testing.assert_close(GENERIC.default_threshold(fourier, 3), threshold, rtol=1e-9, atol=0)
    torch.testing.assert_close(fourier.default_threshold(3), threshold, rtol=1e-9, atol=0)
    modes = GENERIC.modes(fourier, 3, k=3)
    for (R, mass), (R_fast, mass_fast) in zip(modes, fourier.modes(3, k=3), strict=True):
        torch.testing.assert_close(R, R_fast, rtol=0, atol=1e-9)
        torch.testing.assert_close(mass, mass_fast, rtol=0, atol=1e-9)


def test_generic_sampling_follows_the_grid_probabilities(fourier):
    """Gumbel-max draws per chunk: the frequency of each level-1 grid point matches its probability."""
    one = SO3Distribution(fourier.coeffs[:1], lmax=2)
    n = 20000
    _, index = GENERIC.sample(one, n, 1, generator=torch.Generator().manual_seed(1), return_index=True)
    counts = torch.bincount(index[0], minlength=math.prod(so3_grid_size(1))).double()
    expected = one.log_prob_grid(1)[0].exp() * n
    keep = expected > 5
    chi2 = float(((counts[keep] - expected[keep]) ** 2 / expected[keep]).sum())
    assert chi2 < 2 * int(keep.sum()), chi2  # ~dof when right; a wrong law gives thousands
    assert counts[~keep].sum() < 5 * max(1, int((~keep).sum()))


def test_nll_on_grid_is_the_cross_entropy_at_the_nearest_point(fourier):
    R = random_rotations(3, dtype=torch.float64)
    from image2sphere.so3 import so3_healpix_nearest_index

    index = so3_healpix_nearest_index(R, 3)
    dense = -torch.log_softmax(fourier.grid_logits(3), dim=1).gather(1, index[:, None])[:, 0]
    torch.testing.assert_close(fourier.nll_on_grid(R, 3), dense, rtol=0, atol=1e-9)
    torch.testing.assert_close(GENERIC.nll_on_grid(fourier, R, 3), dense, rtol=0, atol=1e-9)


def test_point_estimate_has_a_mode_and_no_density():
    R = random_rotations(4)
    point = PointEstimate(R)
    assert not point.has_density and not point.has_exact_density
    assert torch.equal(point.mode(5), R) and point.sample(3).shape == (4, 3, 3, 3)
    assert all(torch.equal(m[0], r) and float(mass) == 1.0 for (m, mass), r in zip(point.modes(5), R, strict=True))
    with pytest.raises(DensityNotAvailable, match="no density"):
        point.log_density(R[:, None], 3)
    with pytest.raises(ValueError, match=r"\(B, 3, 3\)"):
        PointEstimate(R[0])
    with pytest.raises(ValueError):
        PointEstimate(R * 2)  # not a rotation


# ---------------------------------------------------------------------------------------- regression
def test_6d_representation_is_gram_schmidt():
    torch.manual_seed(0)
    x = torch.randn(100, 6, dtype=torch.float64)
    R = rotation_6d_to_matrix(x)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, torch.eye(3, dtype=torch.float64).expand_as(R))
    torch.testing.assert_close(torch.det(R), torch.ones(100, dtype=torch.float64))
    # first column along a; second in the plane of a and b, on b's side; scale invariant
    a, b = x[:, :3], x[:, 3:]
    torch.testing.assert_close(R[..., 0], a / a.norm(dim=1, keepdim=True))
    assert ((R[..., 1] * b).sum(1) > 0).all() and (torch.det(torch.stack([a, b, R[..., 2]], -1)) > 0).all()
    torch.testing.assert_close(rotation_6d_to_matrix(3 * x), R)
    # the 6D representation of a rotation (its first two columns) gives the rotation back
    Q = random_rotations(10, dtype=torch.float64)
    torch.testing.assert_close(rotation_6d_to_matrix(torch.cat([Q[..., 0], Q[..., 1]], -1)), Q)
    with pytest.raises(ValueError, match=r"\(\.\.\., 6\)"):
        rotation_6d_to_matrix(torch.zeros(2, 9))


def test_special_procrustes_is_the_nearest_rotation_with_a_stable_gradient():
    torch.manual_seed(0)
    M = torch.randn(50, 3, 3, dtype=torch.float64)
    R = project_to_so3(M)
    torch.testing.assert_close(torch.det(R), torch.ones(50, dtype=torch.float64))
    # nearest rotation: against scipy's optimal rotation aligning the identity frame to M's columns
    for m, r in zip(M[:5], R[:5], strict=True):
        ref, _ = ScipyRotation.align_vectors(m.T.numpy(), torch.eye(3, dtype=torch.float64).numpy())
        torch.testing.assert_close(r, torch.from_numpy(ref.as_matrix()), atol=1e-9, rtol=0)
        # and no random rotation is nearer
        Q = random_rotations(200, dtype=torch.float64)
        assert ((Q - m).pow(2).sum((-1, -2)) >= (r - m).pow(2).sum() - 1e-12).all()
    assert torch.autograd.gradcheck(project_to_so3, (M[:4].clone().requires_grad_(),))
    # the polar factor's gradient is finite where the plain SVD gradient is not: repeated singular values
    for degenerate in (torch.eye(3), 2 * random_rotations(1)[0], torch.diag(torch.tensor([1.0, 1.0, 0.5]))):
        X = degenerate.to(torch.float64)[None].clone().requires_grad_()
        (project_to_so3(X) * torch.randn(1, 3, 3, dtype=torch.float64)).sum().backward()
        assert torch.isfinite(X.grad).all()
    # ... and equals autograd through the SVD where that one is defined
    X1, X2 = M[:8].clone().requires_grad_(), M[:8].clone().requires_grad_()
    G = torch.randn(8, 3, 3, dtype=torch.float64)
    (project_to_so3(X1) * G).sum().backward()
    U, _, Vh = torch.linalg.svd(X2)
    D = torch.ones(8, 3, dtype=torch.float64)
    D[:, 2] = torch.det(U @ Vh).detach()
    ((U @ (D[..., None] * Vh)) * G).sum().backward()
    torch.testing.assert_close(X1.grad, X2.grad, atol=1e-9, rtol=0)


class _TinyEncoder(torch.nn.Module):
    out_channels = 4

    def __init__(self):
        super().__init__()
        self.conv = torch.nn.Conv2d(3, 4, 3, padding=1)

    def forward(self, images):
        return self.conv(images)

    def feature_size(self, image_size):
        return (image_size, image_size)


@pytest.mark.parametrize("representation", ["6d", "9d"])
def test_regression_network_loss_and_per_class_layers(representation):
    torch.manual_seed(0)
    net = RotationRegression(_TinyEncoder(), 8, representation=representation, hidden=16)
    R = net(torch.randn(5, 3, 8, 8))
    assert R.shape == (5, 3, 3) and torch.allclose(torch.det(R), torch.ones(5), atol=1e-5)
    target = random_rotations(5)
    # Frobenius loss = |R - R_gt|^2 = 4 (1 - cos angle); geodesic = the angle
    angle = geodesic_distance(R, target)
    torch.testing.assert_close(net.loss(R, target, 3), 4 * (1 - torch.cos(angle)), atol=1e-5, rtol=1e-5)
    geo = RotationRegression(_TinyEncoder(), 8, representation=representation, hidden=16, loss="geodesic")
    torch.testing.assert_close(geo.loss(R, target, 3), angle)
    assert isinstance(net.output_distribution(R), PointEstimate)
    # per-class last layers: the class index picks the layer, classes do not mix
    per_class = RotationRegression(_TinyEncoder(), 8, representation=representation, hidden=16, num_classes=3)
    images = torch.randn(2, 3, 8, 8)
    a = per_class(images, torch.tensor([0, 2]))
    b = per_class(images, torch.tensor([1, 2]))
    assert not torch.allclose(a[0], b[0]) and torch.allclose(a[1], b[1])
    with pytest.raises(ValueError, match="class_index"):
        per_class(images)
    with pytest.raises(ValueError, match="representation"):
        RotationRegression(_TinyEncoder(), 8, representation="4d")


def test_every_grid_point_is_a_rotation_of_the_generic_chunks():
    """The chunks of the generic sweep cover the grid exactly once, in pixel-major order."""
    dist = SO3Distribution(torch.zeros(1, 35, dtype=torch.float64), lmax=2)
    starts, total = [], 0
    for start, rotations in dist._grid_chunks(2):
        starts.append(start)
        ref = so3_healpix_index_to_matrix(torch.arange(start, start + len(rotations)), 2, dtype=torch.float64)
        torch.testing.assert_close(rotations, ref)
        total += len(rotations)
    assert starts[0] == 0 and total == math.prod(so3_grid_size(2))


def test_constants_cached_during_inference_serve_training_later():
    """The per-process caches of grids, index tables and quadrature rules are filled by whichever call comes
    first, often a test loop under ``torch.inference_mode``; what they hold must still be usable by a later
    training step (an inference tensor saved for backward raises). Found when an evaluation and a training
    ran in one process: a matrix Fisher mode on the grid failed after an earlier evaluation."""
    import image2sphere.distributions.matrix_fisher as matrix_fisher
    import image2sphere.metrics as metrics
    import image2sphere.so3.grid_eval as grid_eval
    import image2sphere.so3.wigner as wigner
    from image2sphere.distributions.matrix_fisher import MatrixFisher

    caches = {
        grid_protocol._grid_rotations: (2, torch.float32, "cpu"),
        metrics._flat_grid: (2, torch.float32, "cpu"),
        matrix_fisher._half_interval_rule: (torch.device("cpu"), torch.float64),
        wigner._so3_layout: (2,),
    }
    for cached, args in caches.items():
        cached.cache_clear()
        with torch.inference_mode():
            value = cached(*args)
        tensors = value if isinstance(value, tuple) else (value,)
        assert not any(t.is_inference() for t in tensors), cached.__name__
        cached.cache_clear()
    grid_eval._cached.cache_clear()
    with torch.inference_mode():
        evaluator = grid_eval._cached(2, 2, torch.float32, "cpu")
    assert not any(t.is_inference() for t in vars(evaluator).values() if isinstance(t, torch.Tensor))
    grid_eval._cached.cache_clear()
    # the symptom: an evaluation under inference mode, then a differentiable mode search on the same grid
    grid_protocol._grid_rotations.cache_clear()
    F = torch.randn(2, 3, 3, dtype=torch.float32)
    with torch.inference_mode():
        MatrixFisher(F).mode(2)
    F.requires_grad_(True)
    MatrixFisher(F).grid_logsumexp_and_max(2)[0].sum().backward()
    assert F.grad is not None and torch.isfinite(F.grad).all()
