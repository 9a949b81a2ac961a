"""Tests for the matrix Fisher and Rotation Laplace families (image2sphere.distributions.matrix_fisher,
image2sphere.distributions.rotation_laplace).

The normalisers are checked against references that share no code with the package: a HEALPix grid
sum of the density, a 2D quadrature over the rotation axis (scipy), and the Gaussian limit.
"""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import integrate, special

from conftest import haar_rotations
from image2sphere.distributions.matrix_fisher import (
    MatrixFisher,
    log_scaled_fisher_normalizer,
    matrix_fisher_nll,
)
from image2sphere.distributions.rotation_laplace import (
    RotationLaplace,
    rotation_laplace_log_normalizer,
    rotation_laplace_nll,
)
from image2sphere.so3 import (
    geodesic_distance,
    project_to_so3,
    proper_singular_values,
    rotvec_to_matrix,
    so3_healpix_grid,
)

LOG_PI2 = 2 * math.log(math.pi)
FAMILIES = {"fisher": MatrixFisher, "laplace": RotationLaplace}
NLLS = {"fisher": matrix_fisher_nll, "laplace": rotation_laplace_nll}


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    yield


def random_parameters(b: int, scale: float, seed: int) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    return scale * torch.randn(b, 3, 3, generator=g, dtype=torch.float64)


def c_of(s) -> np.ndarray:
    """``2 (s2 + s3, s1 + s3, s1 + s2)``: the quaternion-space concentrations."""
    s = np.asarray(s, dtype=np.float64)
    return 2 * np.stack([s[..., 1] + s[..., 2], s[..., 0] + s[..., 2], s[..., 0] + s[..., 1]], -1)


# ------------------------------------------------------------------ independent references
def _octant_rule(m: int) -> tuple[np.ndarray, np.ndarray]:
    """Points ``n (m*m, 3)`` and weights (summing to 1) for the mean over S^2 of a function even
    in each coordinate (tensor Gauss-Legendre in ``cos(theta)`` and the azimuth, one octant)."""
    x, w = np.polynomial.legendre.leggauss(m)
    u, wu = (x + 1) / 2, w / 2
    phi, wphi = (x + 1) * np.pi / 4, w / 2
    U, P = np.meshgrid(u, phi, indexing="ij")
    st = np.sqrt(1 - U**2)
    return np.stack([st * np.cos(P), st * np.sin(P), U], -1).reshape(-1, 3), np.outer(wu, wphi).reshape(-1)


def reference_fisher_log_c1hat(s, m: int = 96) -> float:
    """``log E exp(tr(diag(s) R) - sum(s))`` from the axis-angle form: with ``k = n^T diag(c) n``,
    ``E = E_n[i0e(k/2) - i1e(k/2)]`` (the angle integral in closed form)."""
    n, w = _octant_rule(m)
    k = (n**2) @ c_of(s)
    return float(np.log(np.sum(w * (special.i0e(k / 2) - special.i1e(k / 2)))))


def reference_laplace_log_c(s, m: int = 96) -> float:
    """``log`` Rotation Laplace normaliser (Haar volume pi^2) from the axis-angle form:
    ``(4/pi) E_n int_0^{pi/2} sin(p) exp(-a sin(p)) / a dp`` with ``a = sqrt(n^T diag(c) n)``."""
    n, w = _octant_rule(m)
    a = np.sqrt((n**2) @ c_of(s))
    inner, _ = integrate.quad_vec(lambda p: np.sin(p) * np.exp(-a * np.sin(p)) / a, 0, np.pi / 2, epsrel=1e-11)
    return float(np.log(4 / np.pi * np.sum(w * inner))) + LOG_PI2


# ------------------------------------------------------------------ normalisers
MODERATE_S = [[0.5, 0.2, 0.1], [3.0, 2.0, -1.0], [10.0, 5.0, 2.0], [30.0, 20.0, -10.0], [300.0, 200.0, 100.0]]


@pytest.mark.parametrize("s", MODERATE_S)
def test_fisher_normalizer_matches_axis_angle_quadrature(s):
    ours = log_scaled_fisher_normalizer(torch.tensor(s, dtype=torch.float64)).item()
    assert ours == pytest.approx(reference_fisher_log_c1hat(s), abs=1e-6)


@pytest.mark.parametrize("s", MODERATE_S)
def test_laplace_normalizer_matches_axis_angle_quadrature(s):
    ours = rotation_laplace_log_normalizer(torch.tensor([s], dtype=torch.float64)).item()
    assert ours == pytest.approx(reference_laplace_log_c(s), abs=1e-6)


@pytest.mark.parametrize("family", ["fisher", "laplace"])
@pytest.mark.parametrize("scale", [0.3, 1.0, 3.0])
def test_density_integrates_to_one_on_grid(family, scale):
    """Riemann sum over the level-4 HEALPix grid (cell volume pi^2 / N)."""
    grid = so3_healpix_grid(4, dtype=torch.float64)
    dist = FAMILIES[family](random_parameters(3, scale, seed=int(10 * scale)))
    total = torch.logsumexp(dist.exact_log_density(grid), dim=1) + LOG_PI2 - math.log(len(grid))
    # the Laplace density is infinite at its mode: the grid sum is cruder there
    tol = 1e-3 if family == "fisher" else 1e-2
    torch.testing.assert_close(total, torch.zeros(3, dtype=torch.float64), atol=tol, rtol=0)


@pytest.mark.parametrize("scale", [1e3, 1e4])
@pytest.mark.parametrize("shape", [(1.0, 0.7, 0.5), (1.0, 0.9, -0.8), (1.0, 1.0, 1.0), (1.0, 0.6, -0.4)])
def test_concentrated_normalizers_match_gaussian_limit(scale, shape):
    """``c1hat -> 1 / sqrt(pi c_x c_y c_z)`` and ``c_L -> pi^2 4 / (pi sqrt(c_x c_y c_z))`` with
    relative corrections O(1 / min c)."""
    s = torch.tensor([shape], dtype=torch.float64) * scale
    c = c_of(s.numpy())[0]
    log_det = float(np.log(c).sum())
    tol = 10 / c.min()
    fisher = log_scaled_fisher_normalizer(s).item()
    laplace = rotation_laplace_log_normalizer(s).item()
    assert fisher == pytest.approx(-0.5 * math.log(math.pi) - 0.5 * log_det, abs=tol)
    assert laplace == pytest.approx(math.log(4 / math.pi) - 0.5 * log_det + LOG_PI2, abs=tol)
    # the full Fisher normaliser neither overflows nor loses the exp(tr S) factor
    F = torch.diag(s[0])[None]
    log_c = MatrixFisher(F).exact_log_normalizer().item()
    assert log_c == pytest.approx(fisher + float(s.sum()) + LOG_PI2, rel=1e-12)


def test_laplace_normalizer_converged_in_its_quadrature():
    """Halving the mixture step changes nothing (also for nearly degenerate singular values)."""
    import image2sphere.distributions.rotation_laplace as rl

    s = torch.tensor([[5.0, 1.0, -1.0], [5.0, 1e-3, 0.0], [1e4, 1e4, -9999.0], [1e-3, 0, 0]], dtype=torch.float64)
    coarse = rotation_laplace_log_normalizer(s)
    old = rl.LAMBDA_NODES
    try:
        rl.LAMBDA_NODES = 2 * old
        fine = rotation_laplace_log_normalizer(s)
    finally:
        rl.LAMBDA_NODES = old
    torch.testing.assert_close(coarse, fine, atol=1e-7, rtol=0)


def test_uniform_fisher():
    dist = MatrixFisher(torch.zeros(2, 3, 3, dtype=torch.float64))
    ld = dist.exact_log_density(haar_rotations(5, seed=3))
    torch.testing.assert_close(ld, torch.full((2, 5), -LOG_PI2, dtype=torch.float64), atol=1e-12, rtol=0)


# ------------------------------------------------------------------ modes and invariance
@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_mode_is_polar_factor_and_peak(family):
    P = random_parameters(4, 2.0, seed=7)
    P[0] = -torch.diag(torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64))  # det < 0
    dist = FAMILIES[family](P)
    mode = dist.exact_mode()
    torch.testing.assert_close(mode, project_to_so3(P), atol=1e-10, rtol=0)
    torch.testing.assert_close(mode[0], torch.diag(torch.tensor([-1.0, -1.0, 1.0], dtype=torch.float64)))
    torch.testing.assert_close(torch.linalg.det(mode), torch.ones(4, dtype=torch.float64))
    at_mode = dist.unnormalized_log_density(mode[:, None])[:, 0]  # [B]
    others = dist.unnormalized_log_density(haar_rotations(500, seed=1))  # [B, 500]
    near = mode[:, None] @ rotvec_to_matrix(0.01 * torch.randn(4, 50, 3, dtype=torch.float64))
    assert (at_mode[:, None] >= others).all()
    assert (at_mode[:, None] >= dist.unnormalized_log_density(near)).all()
    assert dist.mode(level=2, refine=True).shape == (4, 3, 3)


@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_left_and_right_invariance(family):
    P = random_parameters(3, 2.0, seed=11)
    Q = haar_rotations(3, seed=12)
    R = haar_rotations(6, seed=13)  # [K, 3, 3]
    base = FAMILIES[family](P).exact_log_density(R)  # [B, K]
    left = FAMILIES[family](Q @ P).exact_log_density(Q[:, None] @ R)  # p_{QF}(Q R)
    right = FAMILIES[family](P @ Q).exact_log_density(R @ Q[:, None])  # p_{FQ}(R Q)
    torch.testing.assert_close(left, base, atol=1e-9, rtol=0)
    torch.testing.assert_close(right, base, atol=1e-9, rtol=0)


# ------------------------------------------------------------------ gradients
@pytest.mark.parametrize("family", ["fisher", "laplace"])
@pytest.mark.parametrize("dtype", [torch.float32, torch.float64])
@pytest.mark.parametrize("case", ["zero", "identity", "huge", "huge_negative_det", "random"])
def test_nll_gradients_finite(family, dtype, case):
    B = 4
    P = {
        "zero": torch.zeros(B, 3, 3),
        "identity": torch.eye(3).expand(B, 3, 3) * 1e4,
        "huge": 1e4 * torch.randn(B, 3, 3, generator=torch.Generator().manual_seed(0)),
        "huge_negative_det": -1e4 * torch.eye(3).expand(B, 3, 3) * torch.tensor([1.0, 0.5, 0.25]),
        "random": torch.randn(B, 3, 3, generator=torch.Generator().manual_seed(1)),
    }[case].to(dtype)
    P = P.clone().requires_grad_(True)
    R = haar_rotations(B, seed=2, dtype=dtype)
    R[0] = project_to_so3(P.detach()[0].double()).to(dtype) if case != "zero" else R[0]  # at the mode
    loss = NLLS[family](P, R)
    assert loss.dtype == dtype and loss.shape == (B,)
    assert torch.isfinite(loss).all()
    loss.sum().backward()
    assert torch.isfinite(P.grad).all()


def test_fisher_normalizer_gradient_is_mean_rotation_at_zero():
    """``d log c / dF = E[R]``, which is 0 for the uniform distribution (needs the right
    derivative of ``i0e`` at 0, where the singular values coincide)."""
    F = torch.zeros(1, 3, 3, dtype=torch.float64, requires_grad=True)
    MatrixFisher(F).exact_log_normalizer().sum().backward()
    torch.testing.assert_close(F.grad, torch.zeros_like(F), atol=1e-10, rtol=0)


@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_normalizer_gradcheck(family):
    P = random_parameters(2, 1.5, seed=5)
    P[1] = 2.0 * torch.eye(3, dtype=torch.float64)  # repeated singular values
    P.requires_grad_(True)
    fn = lambda p: FAMILIES[family](p).exact_log_normalizer()  # noqa: E731
    assert torch.autograd.gradcheck(fn, (P,), eps=1e-5, atol=1e-5, rtol=1e-4)


def test_proper_singular_values_sign():
    F = -torch.diag(torch.tensor([3.0, 2.0, 1.0], dtype=torch.float64))[None]
    torch.testing.assert_close(proper_singular_values(F), torch.tensor([[3.0, 2.0, -1.0]], dtype=torch.float64))


# ------------------------------------------------------------------ sampling
def _angle_histogram_check(dist: MatrixFisher | RotationLaplace, n: int, edges: torch.Tensor):
    """Chi-square of the angle-to-mode histogram of ``n`` exact samples against the density summed
    over the level-4 grid; returns the statistic and the number of bins."""
    samples = dist.exact_sample(n, generator=torch.Generator().manual_seed(0))  # [1, n, 3, 3]
    mode = dist.exact_mode()
    angle = geodesic_distance(mode[:, None], samples)[0]
    observed = torch.histogram(angle, bins=edges).hist
    grid = so3_healpix_grid(4, dtype=torch.float64)
    prob = torch.softmax(dist.exact_log_density(grid)[0], dim=0)
    grid_angle = geodesic_distance(mode[0], grid)
    expected = torch.stack(
        [prob[(grid_angle >= lo) & (grid_angle < hi)].sum() for lo, hi in zip(edges[:-1], edges[1:], strict=True)]
    )
    assert float(expected.sum()) == pytest.approx(1.0, abs=1e-9)
    expected = expected * n
    return float(((observed - expected) ** 2 / expected).sum()), len(expected)


@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_exact_samples_match_density(family):
    P = torch.tensor([[[4.0, 1.0, 0.0], [0.5, -2.0, 0.3], [0.0, 0.2, -1.0]]], dtype=torch.float64)
    dist = FAMILIES[family](P)
    edges = torch.linspace(0, math.pi, 13, dtype=torch.float64)
    chi2, bins = _angle_histogram_check(dist, 20000, edges)
    # dof ~ 11: mean 11, sd ~4.7; the grid reference is accurate to ~1e-3 of the mass
    assert chi2 < 45, chi2


def test_fisher_sample_mean_is_normalizer_gradient():
    """``E[R] = d log c / dF`` for a concentrated, anisotropic F with det < 0."""
    F = torch.tensor([[[-20.0, 3.0, 0.0], [1.0, 8.0, 2.0], [0.0, 1.0, 5.0]]], dtype=torch.float64)
    F.requires_grad_(True)
    MatrixFisher(F).exact_log_normalizer().sum().backward()
    samples = MatrixFisher(F.detach()).exact_sample(40000, generator=torch.Generator().manual_seed(1))
    torch.testing.assert_close(samples.mean(1), F.grad, atol=6e-3, rtol=0)
    assert samples.shape == (1, 40000, 3, 3)


def test_laplace_concentrated_sampling_scale():
    """For a concentrated isotropic Rotation Laplace the angle ``theta`` (``t = 4 s sin^2(theta/2)``)
    has ``sqrt(t) ~ Gamma(2, 1)`` in the limit: its mean is 2."""
    s = 1e4
    dist = RotationLaplace(s * torch.eye(3, dtype=torch.float64)[None])
    samples = dist.exact_sample(20000, generator=torch.Generator().manual_seed(2))[0]
    theta = geodesic_distance(torch.eye(3, dtype=torch.float64), samples)
    root_t = torch.sqrt(4 * s * torch.sin(theta / 2) ** 2)
    assert float(root_t.mean()) == pytest.approx(2.0, abs=0.05)
    assert float(root_t.var()) == pytest.approx(2.0, abs=0.15)


# ------------------------------------------------------------------ grid protocol and input checks
@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_grid_protocol_close_to_exact(family):
    dist = FAMILIES[family](random_parameters(2, 0.3, seed=21))
    R = haar_rotations(50, seed=22)
    exact = dist.exact_log_density(R)
    grid = dist.log_density(R, level=3)
    assert dist.has_exact_density
    error = (grid - exact).abs()  # nearest-point error: the Laplace density is steeper (cusp at the mode)
    assert error.mean() < 0.05
    assert error.max() < (0.1 if family == "fisher" else 0.25)


@pytest.mark.parametrize("family", ["fisher", "laplace"])
def test_bad_parameters_raise(family):
    cls = FAMILIES[family]
    for bad in (torch.zeros(3, 3), torch.zeros(2, 3, 4), torch.zeros(0, 3, 3), torch.zeros(2, 3, 3, dtype=torch.long)):
        with pytest.raises(ValueError, match="must"):
            cls(bad)
    nan = torch.zeros(2, 3, 3)
    nan[1, 0, 0] = float("nan")
    with pytest.raises(ValueError, match=r"\(2, 3, 3\)"):
        cls(nan)
    with pytest.raises(ValueError, match="shape of"):
        NLLS[family](torch.zeros(2, 3, 3), torch.eye(3))
    with pytest.raises(ValueError, match=r"^n must be an integer >= 1, got 0"):
        cls(torch.zeros(1, 3, 3)).exact_sample(0)
    with pytest.raises(ValueError, match=r"\(B=2, K, 3, 3\)"):
        cls(torch.zeros(2, 3, 3)).unnormalized_log_density(torch.zeros(3, 5, 3, 3))


def test_generic_set_loss_of_a_pose_network_is_its_loss_averaged_over_each_set():
    """dataset.label=all for a method without a set loss of its own (the matrix Fisher network): the
    loss once per real equivalent rotation of each image, averaged; padding (NaN) never read."""
    from torch import nn

    from image2sphere.nn.heads import MatrixFisherNet

    class Encoder(nn.Module):
        out_channels = 4

        def __init__(self):
            super().__init__()
            self.conv = nn.Conv2d(3, 4, 3, stride=2, padding=1)

        def forward(self, images):
            return self.conv(images)

        def feature_size(self, image_size):
            return image_size // 2, image_size // 2

    torch.manual_seed(0)
    net = MatrixFisherNet(Encoder(), image_size=8, hidden=8).double()
    output = net(torch.randn(3, 3, 8, 8, dtype=torch.float64))
    R = haar_rotations(12, seed=2).reshape(3, 4, 3, 3)
    mask = torch.tensor([[1, 1, 0, 0], [1, 1, 1, 1], [1, 0, 0, 0]], dtype=torch.bool)
    R = R.masked_fill(~mask[..., None, None], float("nan"))
    got = net.set_loss(output, R, mask, 3)
    for b in range(3):
        k = int(mask[b].sum())
        expected = net.loss(output[b : b + 1].expand(k, -1), R[b, :k], 3).mean()
        assert got[b].item() == pytest.approx(expected.item(), rel=1e-12)
    assert torch.isfinite(got).all()
    got.sum().backward()  # differentiable through the repeated rows
    assert all(p.grad is not None for p in net.parameters() if p.requires_grad)
