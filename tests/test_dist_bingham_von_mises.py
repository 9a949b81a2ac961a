"""Tests for the Bingham (mixture) and von Mises (Euler angle mixture) pose distributions.

References are independent of the code under test: mpmath quadrature, Monte Carlo on S^3, the
Laplace approximation, trapezoid rules on circles and tori, HEALPix grid sums, explicit matrices.
"""

from __future__ import annotations

import math

import mpmath
import pytest
import torch

from conftest import haar_rotations
from image2sphere.distributions.bingham import (
    Bingham,
    bingham_log_normalizer,
    bingham_nll,
    bingham_params_from_output,
    quaternion_basis_matrix,
)
from image2sphere.distributions.von_mises import (
    VonMisesEuler,
    von_mises_log_normalizer,
    von_mises_nll,
    von_mises_params_from_output,
)
from image2sphere.so3 import (
    aet_to_matrix,
    geodesic_distance,
    matrix_to_aet_biternions,
    matrix_to_quaternion_outer,
    quaternion_multiply,
    quaternion_to_matrix,
    rotvec_to_matrix,
    so3_healpix_grid,
    so3_healpix_nearest_index,
)

D = torch.float64
PI2 = math.pi**2


@pytest.fixture(autouse=True)
def _one_thread(single_thread):
    yield


def unit(x: torch.Tensor) -> torch.Tensor:
    return x / torch.linalg.vector_norm(x, dim=-1, keepdim=True)


def biternion(angles) -> torch.Tensor:
    a = torch.as_tensor(angles, dtype=D)
    return torch.stack([a.cos(), a.sin()], dim=-1)


def grid_mass(dist, level: int) -> torch.Tensor:
    """``sum_i p(R_i) pi^2 / N`` over the (equal volume) HEALPix grid: ``(B,)``."""
    G = so3_healpix_grid(level, dtype=D).reshape(-1, 3, 3)
    total = 0
    for i in range(0, len(G), 1 << 16):
        total = total + dist.exact_log_density(G[i : i + (1 << 16)]).exp().sum(dim=1)
    return total * PI2 / len(G)


def random_bingham(z, C: int = 2, seed: int = 0) -> Bingham:
    g = torch.Generator().manual_seed(seed)
    z = torch.as_tensor(z, dtype=D).expand(1, C, 3).clone()
    q = unit(torch.randn(1, C, 4, generator=g, dtype=D))
    w = torch.softmax(torch.randn(1, C, generator=g, dtype=D), dim=-1)
    return Bingham(quaternion_basis_matrix(q), z, w)


def histogram_check(dist, seed: int = 0, n: int = 20000):
    """Sample frequencies over the 72 cells (nearest level-0 grid point) against the cell masses
    of the density (level-4 grid quadrature); returns the max |difference| in units of the std."""
    samples = dist.exact_sample(n, generator=torch.Generator().manual_seed(seed))[0]
    assert samples.shape == (n, 3, 3)
    freq = torch.bincount(so3_healpix_nearest_index(samples, 0), minlength=72).to(D) / n
    G = so3_healpix_grid(4, dtype=D).reshape(-1, 3, 3)
    mass = dist.exact_log_density(G).exp()[0] * PI2 / len(G)
    cells = torch.zeros(72, dtype=D).index_add_(0, so3_healpix_nearest_index(G, 0), mass)
    std = torch.sqrt(cells * (1 - cells) / n) + 1e-3
    return ((freq - cells).abs() / std).max().item(), cells.sum().item()


# ================================================================================== Bingham
def mp_log_normalizer(z) -> float:
    """log(F(Z) / 2) by mpmath quadrature of the exact 1D integral (30 digits)."""
    with mpmath.workdps(30):
        z1, z2, z3 = (mpmath.mpf(float(v)) for v in z)

        def f(t):
            return (
                mpmath.exp(z2 * t)
                * mpmath.besseli(0, (z1 - z2) * t / 2)
                * mpmath.exp(-abs((z1 - z2) * t / 2))
                * mpmath.besseli(0, z3 * (1 - t) / 2)
                * mpmath.exp(-abs(z3 * (1 - t) / 2))
            )

        points = [0] + [mpmath.mpf(10) ** -k for k in range(8, 0, -1)] + [1]
        return float(mpmath.log(mpmath.pi**2 * mpmath.quad(f, points)))


@pytest.mark.parametrize(
    "z", [(0, 0, 0), (-1, -0.5, -0.1), (-40, -10, -2), (-1e3, -1e3, -1e3), (-1e3, -500, -1e-3), (-6e4, -3e4, -1e4)]
)
def test_bingham_normalizer_matches_mpmath(z):
    value = bingham_log_normalizer(torch.tensor(z, dtype=D)).item()
    assert value == pytest.approx(mp_log_normalizer(z), abs=1e-10)


def test_bingham_normalizer_independent_references():
    # uniform: pi^2 (Haar volume)
    assert bingham_log_normalizer(torch.zeros(3, dtype=D)).item() == pytest.approx(math.log(PI2), abs=1e-12)
    # Monte Carlo on S^3: log((2 pi^2 / 2) E_uniform[exp(q^T Z q)])
    g = torch.Generator().manual_seed(0)
    q = unit(torch.randn(400_000, 4, generator=g, dtype=D))
    for z in [(-2.0, -1.0, -0.5), (-8.0, -3.0, -0.2)]:
        zt = torch.tensor([*z, 0.0], dtype=D)
        mc = math.log(PI2 * torch.exp((q**2 * zt).sum(-1)).mean().item())
        assert bingham_log_normalizer(torch.tensor(z, dtype=D)).item() == pytest.approx(mc, abs=5e-3)
    # Laplace: two antipodal Gaussian peaks, F ~ 2 pi^{3/2} / sqrt(|z1 z2 z3|) (relative error O(1/|z|))
    z = (-2e4, -1e4, -5e3)
    laplace = math.log(math.pi**1.5 / math.sqrt(abs(z[0] * z[1] * z[2])))
    assert bingham_log_normalizer(torch.tensor(z, dtype=D)).item() == pytest.approx(laplace, abs=1e-3)


@pytest.mark.parametrize("z", [(-1.0, -0.5, -0.1), (-50.0, -20.0, -5.0), (-400.0, -300.0, -100.0)])
def test_bingham_grid_normalisation(z):
    dist = random_bingham(z, C=2, seed=1)
    assert grid_mass(dist, 4).item() == pytest.approx(1.0, abs=1e-3)


def test_quaternion_outer_and_basis():
    q = unit(torch.randn(50, 4, dtype=D, generator=torch.Generator().manual_seed(2)))
    torch.testing.assert_close(matrix_to_quaternion_outer(quaternion_to_matrix(q, "wxyz")), q[:, :, None] * q[:, None])
    M = quaternion_basis_matrix(q)
    torch.testing.assert_close(M.transpose(-1, -2) @ M, torch.eye(4, dtype=D).expand(50, 4, 4))
    torch.testing.assert_close(M[..., 3], q)
    p = unit(torch.randn(50, 4, dtype=D))
    R = quaternion_to_matrix(quaternion_multiply(p, q), "wxyz")
    torch.testing.assert_close(R, quaternion_to_matrix(p, "wxyz") @ quaternion_to_matrix(q, "wxyz"))


def test_bingham_params_layout_and_mode():
    x = torch.randn(3, 16, dtype=D, generator=torch.Generator().manual_seed(3))
    M, z, w = bingham_params_from_output(x, 2)
    assert M.shape == (3, 2, 4, 4) and z.shape == (3, 2, 3) and w.shape == (3, 2)
    assert (z <= 0).all() and (z[..., :-1] <= z[..., 1:]).all()
    torch.testing.assert_close(w.sum(-1), torch.ones(3, dtype=D))
    torch.testing.assert_close(M[..., 3], unit(x.view(3, 2, 8)[..., :4]))
    # mode = the peak: above every level-3 grid point and every small perturbation
    dist = Bingham.from_output(x[:, :8], 1)
    mode = dist.exact_mode()
    torch.testing.assert_close(mode, quaternion_to_matrix(unit(x[:, :4]), "wxyz"))
    at_mode = dist.exact_log_density(mode[:, None])
    G = so3_healpix_grid(3, dtype=D).reshape(-1, 3, 3)
    assert (dist.exact_log_density(G) <= at_mode + 1e-12).all()
    near = mode[:, None] @ rotvec_to_matrix(0.05 * torch.randn(3, 100, 3, dtype=D))
    assert (dist.exact_log_density(near) < at_mode).all()
    # a mixture: the best component mode beats the other one
    dist2 = Bingham.from_output(x, 2)
    best = dist2.exact_log_density(dist2.exact_mode()[:, None])[:, 0]
    assert (best >= dist2.exact_log_density(dist2.component_modes()).amax(1) - 1e-12).all()


def test_bingham_left_invariance():
    x = torch.randn(2, 24, dtype=D, generator=torch.Generator().manual_seed(4))
    x[:, 4:7] += 2.0
    qQ = unit(torch.randn(2, 4, dtype=D))
    xQ = x.clone().view(2, 3, 8)
    xQ[..., :4] = quaternion_multiply(qQ[:, None], unit(xQ[..., :4]))
    Q = quaternion_to_matrix(qQ, "wxyz")  # [2, 3, 3]
    R = haar_rotations(20, seed=5).expand(2, 20, 3, 3)
    p = Bingham.from_output(x, 3).exact_log_density(R)
    pQ = Bingham.from_output(xQ.view(2, 24), 3).exact_log_density(Q[:, None] @ R)
    torch.testing.assert_close(pQ, p)
    # antipodal symmetry: q and -q give the same distribution
    xN = x.clone().view(2, 3, 8)
    xN[..., :4] *= -1
    torch.testing.assert_close(Bingham.from_output(xN.view(2, 24), 3).exact_log_density(R), p)


def test_bingham_sampling_matches_density():
    dist = random_bingham((-6.0, -2.0, -0.5), C=2, seed=6)
    worst, total = histogram_check(dist, seed=0)
    assert total == pytest.approx(1.0, abs=1e-3)
    assert worst < 5.0
    # and a concentrated one: samples within a few degrees of the mode, at the right spread
    sharp = random_bingham((-2000.0, -1000.0, -500.0), C=1, seed=7)
    s = sharp.exact_sample(4000, generator=torch.Generator().manual_seed(1))
    angle = geodesic_distance(s[0], sharp.exact_mode()[0])
    # rotation angle 2 |v|, v ~ N(0, diag(1 / (2 |z_i|))): E[angle^2] = 4 sum 1 / (2 |z_i|)
    expected = 4 * sum(1 / (2 * v) for v in (2000.0, 1000.0, 500.0))
    assert (angle**2).mean().item() == pytest.approx(expected, rel=0.1)


def test_bingham_grid_protocol_broad():
    dist = random_bingham((-1.5, -0.8, -0.3), C=2, seed=8)
    R = haar_rotations(30, seed=9)
    torch.testing.assert_close(dist.log_density(R, level=3), dist.exact_log_density(R), atol=0.05, rtol=0)
    assert dist.has_exact_density


def test_bingham_gradients_finite_float32():
    x = torch.tensor(
        [[0.3, -1.0, 0.2, 0.5, 30.0, 30.0, 30.0, 0.0], [1e-8, 0.0, 0.0, 0.0, -30.0, -30.0, -30.0, 50.0]],
        dtype=torch.float32,
    ).repeat(1, 2)
    x[:, 15] = -50.0
    x.requires_grad_(True)
    R = haar_rotations(2, seed=10, dtype=torch.float32)
    R[0] = quaternion_to_matrix(x[0, :4].detach(), "wxyz")  # at the mode of a component
    loss = bingham_nll(x, R, num_components=2)
    assert torch.isfinite(loss).all()
    loss.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_bingham_bad_input():
    with pytest.raises(ValueError, match=r"\(3, 7\)"):
        bingham_params_from_output(torch.zeros(3, 7), 1)
    with pytest.raises(ValueError, match="num_components"):
        bingham_params_from_output(torch.zeros(3, 8), 0)
    with pytest.raises(ValueError, match=r"\(2, 1, 3\)"):
        Bingham(torch.eye(4).expand(2, 1, 4, 4), torch.zeros(2, 1, 3) + 1)
    with pytest.raises(ValueError, match=r"\(2, 1, 2\)"):
        Bingham(torch.eye(4).expand(2, 1, 4, 4), torch.zeros(2, 1, 2))
    with pytest.raises(ValueError, match="orthonormal"):
        Bingham(2 * torch.eye(4).expand(2, 1, 4, 4), torch.zeros(2, 1, 3))


# ================================================================================== von Mises
def axis_rotation(axis: int, angle: float) -> torch.Tensor:
    c, s = math.cos(angle), math.sin(angle)
    i, j = [(1, 2), (2, 0), (0, 1)][axis]
    R = torch.eye(3, dtype=D)
    R[i, i] = R[j, j] = c
    R[j, i], R[i, j] = s, -s
    return R


def test_euler_chart():
    g = torch.Generator().manual_seed(11)
    a, e, t = (torch.rand(200, generator=g, dtype=D) * 2 * math.pi - math.pi for _ in range(3))
    R = aet_to_matrix(a, e, t)
    for k in range(3):
        explicit = axis_rotation(0, -t[k].item()) @ axis_rotation(1, -e[k].item()) @ axis_rotation(2, -a[k].item())
        torch.testing.assert_close(R[k], explicit)
    # RenderForCNN's passive Tz(a) = Rz(-a)
    torch.testing.assert_close(axis_rotation(2, -0.3)[0, 1], torch.tensor(math.sin(0.3), dtype=D))
    torch.testing.assert_close(aet_to_matrix(a + math.pi, math.pi - e, t + math.pi), R)  # 2:1
    ba, be, bt = matrix_to_aet_biternions(R)
    sign = torch.sign(torch.cos(e))[:, None]  # the preimage with cos e >= 0
    torch.testing.assert_close(ba, sign * biternion(a))
    torch.testing.assert_close(bt, sign * biternion(t))
    torch.testing.assert_close(be, biternion(torch.where(sign[:, 0] > 0, e, math.pi - e)))


@pytest.mark.parametrize("kappa", [1e-3, 0.7, 12.0, 900.0, 1e5])
def test_von_mises_normalizer_trapezoid(kappa):
    x = torch.linspace(0, 2 * math.pi, 40001, dtype=D)[:-1]  # trapezoid: spectral on a circle
    ref = math.log((torch.exp(kappa * (torch.cos(x) - 1)).sum() * 2 * math.pi / len(x)).item()) + kappa
    assert von_mises_log_normalizer(torch.tensor(kappa, dtype=D)).item() == pytest.approx(ref, abs=1e-10)


CASES = [  # (kappa (3,), mean angles (3,)): broad, moderate, concentrated; elevation away from +-pi/2
    ([0.3, 0.5, 1.0], [0.3, 0.9, -2.0]),
    ([5.0, 10.0, 3.0], [1.0, 0.4, 2.0]),
    ([300.0, 500.0, 200.0], [0.1, 0.2, 0.3]),
]


def vm(kappa, angles, **kwargs) -> VonMisesEuler:
    return VonMisesEuler(biternion(angles)[None, None], torch.tensor(kappa, dtype=D)[None, None], **kwargs)


@pytest.mark.parametrize("kappa, angles", CASES)
def test_von_mises_grid_normalisation(kappa, angles):
    assert grid_mass(vm(kappa, angles), 4).item() == pytest.approx(1.0, abs=2e-3)


def test_von_mises_torus_normalisation_mixture():
    """Over the torus the density times the Haar Jacobian |cos e| / 8 integrates to 2 (double cover)."""
    mu = biternion(torch.tensor([[[0.3, 1.3, -2.0], [2.0, -0.5, 1.0]]]))  # [1, 2, 3, 2]
    dist = VonMisesEuler(mu, torch.tensor([[[0.5, 2.0, 1.0], [3.0, 1.0, 4.0]]], dtype=D), jacobian_floor=0.0)
    n = 48
    x = (torch.arange(n, dtype=D) + 0.5) * 2 * math.pi / n  # cos e != 0 at every node
    a, e, t = torch.meshgrid(x, x, x, indexing="ij")
    R = aet_to_matrix(a.flatten(), e.flatten(), t.flatten())
    integrand = dist.exact_log_density(R).exp()[0] * e.flatten().cos().abs() / 8
    assert (integrand.sum() * (2 * math.pi / n) ** 3).item() == pytest.approx(2.0, abs=1e-9)


def test_von_mises_params_mode_and_peak():
    x = torch.randn(2, 20, dtype=D, generator=torch.Generator().manual_seed(12))
    mu, kappa, w = von_mises_params_from_output(x, 2)
    assert mu.shape == (2, 2, 3, 2) and kappa.shape == (2, 2, 3) and (kappa > 0).all()
    torch.testing.assert_close(mu, unit(x.view(2, 2, 10)[..., :6].reshape(2, 2, 3, 2)))
    torch.testing.assert_close(w.sum(-1), torch.ones(2, dtype=D))
    # one component with mean elevation 0: the mean rotation is the SO(3) peak
    dist = vm([20.0, 8.0, 5.0], [0.7, 0.0, -1.1])
    mode = dist.exact_mode()
    torch.testing.assert_close(mode[0], aet_to_matrix(*torch.tensor([0.7, 0.0, -1.1], dtype=D)))
    at_mode = dist.exact_log_density(mode[:, None])
    G = so3_healpix_grid(3, dtype=D).reshape(-1, 3, 3)
    assert (dist.exact_log_density(G) <= at_mode).all()
    near = mode[:, None] @ rotvec_to_matrix(0.05 * torch.randn(1, 100, 3, dtype=D))
    assert (dist.exact_log_density(near) < at_mode).all()
    mix = VonMisesEuler.from_output(x, 2)
    best = mix.exact_log_density(mix.exact_mode()[:, None])[:, 0]
    assert (best >= mix.exact_log_density(mix.component_means()).amax(1) - 1e-12).all()


def test_von_mises_sampling_matches_density():
    mu = biternion(torch.tensor([[[0.3, 0.6, -2.0], [2.5, -0.4, 1.0]]]))
    dist = VonMisesEuler(mu, torch.tensor([[[2.0, 4.0, 1.0], [3.0, 6.0, 2.0]]], dtype=D), torch.tensor([[0.3, 0.7]]))
    worst, total = histogram_check(dist, seed=1)
    assert total == pytest.approx(1.0, abs=2e-3)
    assert worst < 5.0
    # the sampled angles of a single concentrated component have the von Mises mean resultant
    sharp = vm([50.0, 200.0, 1e4], [1.0, -0.3, 2.0])
    a, e, t = matrix_to_aet_biternions(sharp.exact_sample(5000, generator=torch.Generator().manual_seed(2))[0])
    for b, k, m in zip((a, e, t), (50.0, 200.0, 1e4), (1.0, -0.3, 2.0), strict=True):
        resultant = (b @ biternion(m)).mean().item()
        expected = (torch.special.i1e(torch.tensor(k)) / torch.special.i0e(torch.tensor(k))).item()
        assert resultant == pytest.approx(expected, abs=4 * math.sqrt(1 - expected**2) / math.sqrt(5000) + 1e-4)


def test_von_mises_grid_protocol_broad():
    dist = vm([0.5, 0.8, 0.3], [0.3, 0.2, -2.0])
    R = haar_rotations(30, seed=13)
    R = R[matrix_to_aet_biternions(R)[1][:, 0] > 0.5]  # away from gimbal lock (density ~ 1 / |cos e|)
    assert len(R) > 15
    torch.testing.assert_close(dist.log_density(R, level=3), dist.exact_log_density(R), atol=0.1, rtol=0)


def test_von_mises_gradients_finite_float32():
    x = torch.zeros(3, 20, dtype=torch.float32)
    x[:, 0:6] = torch.tensor([1.0, 0.0, 1e-8, 0.0, 0.0, 1.0])
    x[0, 6:9], x[1, 6:9], x[2, 6:9] = 1e4, -50.0, 0.0
    x[:, 10:16] = torch.tensor([0.0, -1.0, 1.0, 1.0, -1.0, 0.0])
    x[:, 19] = torch.tensor([50.0, -50.0, 0.0])
    x.requires_grad_(True)
    R = torch.stack(
        [
            aet_to_matrix(*torch.tensor([0.0, 0.0, math.pi / 2])),  # at the mean of a kappa = 1e4 component
            aet_to_matrix(*torch.tensor([0.2, math.pi / 2, 0.1])),  # gimbal lock
            haar_rotations(1, seed=14, dtype=torch.float32)[0],
        ]
    ).float()
    loss = von_mises_nll(x, R, num_components=2)
    assert torch.isfinite(loss).all()
    loss.sum().backward()
    assert torch.isfinite(x.grad).all()


def test_von_mises_bad_input():
    with pytest.raises(ValueError, match=r"\(2, 9\)"):
        von_mises_params_from_output(torch.zeros(2, 9), 1)
    with pytest.raises(ValueError, match=r"\(1, 1, 3\)"):
        VonMisesEuler(torch.ones(1, 1, 3, 2), torch.zeros(1, 1, 3))
    with pytest.raises(ValueError, match=r"\(1, 1, 2, 2\)"):
        VonMisesEuler(torch.ones(1, 1, 2, 2), torch.ones(1, 1, 2))
    with pytest.raises(ValueError, match=r"\(2, 3, 3\)"):
        von_mises_nll(torch.ones(1, 10), torch.eye(3).expand(2, 3, 3))


def test_von_mises_component_normalizers_are_the_product_of_three_circle_normalizers():
    """Quick. ``component_log_normalizers``: per component, log of prod_i 2 pi I0(kappa_i) (mpmath's Bessel)."""
    kappa = torch.tensor([[[0.3, 5.0, 40.0], [1e-3, 2.0, 700.0]]], dtype=D)  # [B=1, C=2, 3]
    dist = VonMisesEuler(biternion(torch.zeros(1, 2, 3, dtype=D)), kappa)
    ref = [sum(float(mpmath.log(2 * mpmath.pi * mpmath.besseli(0, k))) for k in row) for row in kappa[0].tolist()]
    torch.testing.assert_close(dist.component_log_normalizers(), torch.tensor([ref], dtype=D), rtol=1e-12, atol=0)
