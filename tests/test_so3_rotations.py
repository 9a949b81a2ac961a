"""Tests for image2sphere.so3.rotations against scipy / e3nn and mathematical properties."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from e3nn import o3
from scipy.spatial.transform import Rotation

from conftest import haar_rotations
from image2sphere.so3 import (
    aet_biternions_to_matrix,
    aet_to_matrix,
    angles_to_matrix,
    check_rotation_matrix,
    geodesic_distance,
    geodesic_distance_deg,
    matrix_to_aet_biternions,
    matrix_to_angles,
    matrix_to_quaternion,
    project_to_so3,
    proper_svd,
    quaternion_multiply,
    quaternion_to_matrix,
    random_rotations,
    rotation_about_axis,
    rotation_group,
    rotvec_to_matrix,
)

FLIP = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))  # rotation by pi about x


def assert_is_rotation(R: torch.Tensor, atol: float = 1e-10) -> None:
    eye = torch.eye(3, dtype=R.dtype).expand_as(R)
    torch.testing.assert_close(R.transpose(-1, -2) @ R, eye, atol=atol, rtol=0)
    torch.testing.assert_close(torch.linalg.det(R), torch.ones(R.shape[:-2], dtype=R.dtype), atol=atol, rtol=0)


# ---------------------------------------------------------------------------------- geodesic distance
def test_geodesic_distance_matches_scipy():
    r1 = Rotation.random(200, random_state=1)
    r2 = Rotation.random(200, random_state=2)
    expected = (r1.inv() * r2).magnitude()
    R1 = torch.as_tensor(r1.as_matrix())
    R2 = torch.as_tensor(r2.as_matrix())
    got = geodesic_distance(R1, R2)
    assert got.shape == (200,)
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-7, rtol=0)  # acos near 0/pi loses digits
    np.testing.assert_allclose(geodesic_distance_deg(R1, R2).numpy(), np.degrees(expected), atol=1e-5)
    # symmetric and broadcasting
    torch.testing.assert_close(geodesic_distance(R2, R1), got, atol=1e-12, rtol=0)
    torch.testing.assert_close(geodesic_distance(R1[:, None], R2[None, :3]).diagonal()[:3], got[:3])


def test_geodesic_distance_exact_values():
    R = haar_rotations(5, seed=3)
    assert torch.equal(
        geodesic_distance(torch.eye(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)),
        torch.tensor(0.0, dtype=torch.float64),
    )
    d0 = geodesic_distance(R, R)
    assert torch.all(d0 >= 0)
    assert torch.all(d0 < 1e-7)
    d_pi = geodesic_distance(R, R @ FLIP)
    torch.testing.assert_close(d_pi, torch.full((5,), math.pi, dtype=torch.float64), atol=1e-7, rtol=0)
    # exact identity / exact pi with integer-valued matrices
    eye = torch.eye(3, dtype=torch.float64)
    assert geodesic_distance(eye, eye).item() == 0.0
    assert geodesic_distance(eye, FLIP).item() == pytest.approx(math.pi, abs=1e-15)
    # a rotation by a known angle about z
    t = 0.7
    Rz = torch.tensor([[math.cos(t), -math.sin(t), 0], [math.sin(t), math.cos(t), 0], [0, 0, 1]], dtype=torch.float64)
    assert geodesic_distance(eye, Rz).item() == pytest.approx(t, abs=1e-12)


@pytest.mark.parametrize("case", ["identity", "pi"])
def test_geodesic_distance_gradient_finite(case):
    R1 = haar_rotations(4, seed=5)
    R2 = R1.clone() if case == "identity" else R1 @ FLIP
    R1 = R1.clone().requires_grad_(True)
    R2 = R2.clone().requires_grad_(True)
    d = geodesic_distance(R1, R2)
    d.sum().backward()
    assert torch.isfinite(R1.grad).all()
    assert torch.isfinite(R2.grad).all()
    # the exact identity case too (trace exactly 3)
    eye = torch.eye(3, dtype=torch.float64, requires_grad=True)
    geodesic_distance(eye, torch.eye(3, dtype=torch.float64)).backward()
    assert torch.isfinite(eye.grad).all()


def test_geodesic_distance_gradient_matches_analytic_away_from_singularities():
    R1 = haar_rotations(6, seed=6)
    R2 = haar_rotations(6, seed=7).requires_grad_(True)
    geodesic_distance(R1, R2).sum().backward()
    # d/dR2 acos((tr(R1^T R2) - 1)/2) = -R1 / (2 sqrt(1 - x^2))
    x = ((R1 * R2.detach()).sum(dim=(-1, -2)) - 1) / 2
    expected = -R1 / (2 * torch.sqrt(1 - x**2))[:, None, None]
    torch.testing.assert_close(R2.grad, expected, atol=1e-10, rtol=1e-8)


def test_geodesic_distance_bad_shape():
    with pytest.raises(ValueError):
        geodesic_distance(torch.eye(3), torch.zeros(3, 4))


# ---------------------------------------------------------------------------------- quaternions
def test_quaternion_to_matrix_matches_scipy():
    q_xyzw = np.random.default_rng(0).normal(size=(100, 4))
    expected = Rotation.from_quat(q_xyzw).as_matrix()  # scipy is scalar-last and normalises
    got_xyzw = quaternion_to_matrix(torch.as_tensor(q_xyzw), order="xyzw")
    np.testing.assert_allclose(got_xyzw.numpy(), expected, atol=1e-12)
    q_wxyz = q_xyzw[:, [3, 0, 1, 2]]
    got_wxyz = quaternion_to_matrix(torch.as_tensor(q_wxyz), order="wxyz")
    np.testing.assert_allclose(got_wxyz.numpy(), expected, atol=1e-12)
    assert_is_rotation(got_wxyz)


def test_quaternion_to_matrix_scalar_first_scipy():
    q = np.random.default_rng(1).normal(size=(20, 4))
    try:
        expected = Rotation.from_quat(q, scalar_first=True).as_matrix()
    except TypeError:  # scipy < 1.14
        pytest.skip("scipy without scalar_first")
    np.testing.assert_allclose(quaternion_to_matrix(torch.as_tensor(q), order="wxyz").numpy(), expected, atol=1e-12)


def test_quaternion_known_values_and_sign_invariance():
    # 90 degrees about z, wxyz = (cos 45, 0, 0, sin 45)
    q = torch.tensor([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)], dtype=torch.float64)
    expected = torch.tensor([[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]], dtype=torch.float64)
    torch.testing.assert_close(quaternion_to_matrix(q, order="wxyz"), expected, atol=1e-15, rtol=0)
    torch.testing.assert_close(quaternion_to_matrix(q.roll(-1), order="xyzw"), expected, atol=1e-15, rtol=0)
    # unnormalised and batched (2, 5, 4)
    qs = torch.randn(2, 5, 4, dtype=torch.float64, generator=torch.Generator().manual_seed(3))
    R = quaternion_to_matrix(qs, order="wxyz")
    assert R.shape == (2, 5, 3, 3)
    torch.testing.assert_close(quaternion_to_matrix(-qs, order="wxyz"), R, atol=1e-14, rtol=0)
    torch.testing.assert_close(quaternion_to_matrix(3.5 * qs, order="wxyz"), R, atol=1e-14, rtol=0)
    assert_is_rotation(R)


def test_quaternion_bad_input():
    q = torch.tensor([1.0, 0.0, 0.0, 0.0])
    for order in ("wxzy", "", "WXYZ", None):
        with pytest.raises(ValueError):
            quaternion_to_matrix(q, order=order)
    with pytest.raises(ValueError):
        quaternion_to_matrix(torch.ones(3), order="wxyz")
    with pytest.raises(ValueError):
        quaternion_to_matrix(torch.ones(5, 3), order="xyzw")
    with pytest.raises(ValueError):
        quaternion_to_matrix(torch.zeros(4), order="wxyz")


# ---------------------------------------------------------------------------------- Euler angles
def test_angles_to_matrix_matches_e3nn_and_explicit_product():
    g = torch.Generator().manual_seed(4)
    a, b, c = (torch.rand(50, generator=g, dtype=torch.float64) * s for s in (2 * math.pi, math.pi, 2 * math.pi))
    R = angles_to_matrix(a, b, c)
    torch.testing.assert_close(R, o3.angles_to_matrix(a, b, c), atol=1e-14, rtol=0)

    def ry(t):
        return torch.tensor(
            [[math.cos(t), 0, math.sin(t)], [0, 1, 0], [-math.sin(t), 0, math.cos(t)]], dtype=torch.float64
        )

    def rx(t):
        return torch.tensor(
            [[1, 0, 0], [0, math.cos(t), -math.sin(t)], [0, math.sin(t), math.cos(t)]], dtype=torch.float64
        )

    for i in range(5):
        expected = ry(a[i].item()) @ rx(b[i].item()) @ ry(c[i].item())
        torch.testing.assert_close(R[i], expected, atol=1e-14, rtol=0)


def test_matrix_to_angles_round_trip_and_e3nn():
    R = haar_rotations(300, seed=8)
    a, b, c = matrix_to_angles(R)
    assert a.shape == b.shape == c.shape == (300,)
    assert torch.all((b >= 0) & (b <= math.pi))
    assert torch.all((a > -math.pi - 1e-12) & (a <= math.pi + 1e-12))
    assert torch.all((c > -math.pi - 1e-12) & (c <= math.pi + 1e-12))
    torch.testing.assert_close(angles_to_matrix(a, b, c), R, atol=1e-10, rtol=0)
    ea, eb, ec = o3.matrix_to_angles(R)
    torch.testing.assert_close(b, eb, atol=1e-10, rtol=0)
    # alpha, gamma agree with e3nn modulo 2 pi
    for x, y in ((a, ea), (c, ec)):
        diff = torch.remainder(x - y + math.pi, 2 * math.pi) - math.pi
        assert diff.abs().max() < 1e-10
    # angles -> matrix -> angles (away from beta = 0, pi)
    g = torch.Generator().manual_seed(9)
    a0 = (torch.rand(100, generator=g, dtype=torch.float64) * 2 - 1) * (math.pi - 0.01)
    b0 = 0.05 + torch.rand(100, generator=g, dtype=torch.float64) * (math.pi - 0.1)
    c0 = (torch.rand(100, generator=g, dtype=torch.float64) * 2 - 1) * (math.pi - 0.01)
    a1, b1, c1 = matrix_to_angles(angles_to_matrix(a0, b0, c0))
    for x, y in ((a0, a1), (b0, b1), (c0, c1)):
        torch.testing.assert_close(x, y, atol=1e-10, rtol=0)


def test_matrix_to_angles_degenerate_beta_and_float32():
    # beta = 0 and pi: only alpha +- gamma determined, but the matrix must round trip
    a = torch.tensor([0.3, -1.0, 2.0, 0.0], dtype=torch.float64)
    b = torch.tensor([0.0, 0.0, math.pi, math.pi], dtype=torch.float64)
    c = torch.tensor([1.1, 0.4, -0.5, 0.0], dtype=torch.float64)
    R = angles_to_matrix(a, b, c)
    torch.testing.assert_close(angles_to_matrix(*matrix_to_angles(R)), R, atol=1e-10, rtol=0)
    # float32 input whose det is not exactly 1 is accepted (e3nn would assert)
    R32 = haar_rotations(50, seed=10, dtype=torch.float32)
    back = angles_to_matrix(*matrix_to_angles(R32))
    torch.testing.assert_close(back, R32, atol=1e-5, rtol=0)
    with pytest.raises(ValueError):
        matrix_to_angles(2 * torch.eye(3))


# ---------------------------------------------------------------------------------- checks and projection
@pytest.mark.parametrize(
    "bad",
    [
        torch.zeros(3, 4),
        torch.zeros(3),
        torch.zeros(2, 4, 3),
        2 * torch.eye(3),
        torch.diag(torch.tensor([1.0, 1.0, -1.0])),
        torch.full((3, 3), float("nan")),
        torch.eye(3, dtype=torch.long),
        torch.stack([torch.eye(3), torch.diag(torch.tensor([-1.0, 1.0, 1.0]))]),
    ],
    ids=["3x4", "vector", "2x4x3", "scaled", "reflection", "nan", "integer", "one-bad-in-batch"],
)
def test_check_rotation_matrix_rejects(bad):
    with pytest.raises(ValueError):
        check_rotation_matrix(bad)


def test_check_rotation_matrix_accepts_and_returns_input():
    R = haar_rotations(7, seed=11).reshape(7, 1, 3, 3)
    assert check_rotation_matrix(R) is R
    R32 = R.float()
    assert check_rotation_matrix(R32) is R32
    nan_in_one = R.clone()
    nan_in_one[3, 0, 1, 1] = float("nan")
    with pytest.raises(ValueError):
        check_rotation_matrix(nan_in_one)
    with pytest.raises(ValueError):
        check_rotation_matrix(R.numpy())
    # tolerance: a perturbation of 1e-3 fails at the default atol but passes a loose one
    P = R[0, 0] + 1e-3 * torch.ones(3, 3, dtype=torch.float64)
    with pytest.raises(ValueError):
        check_rotation_matrix(P)
    check_rotation_matrix(P, atol=1e-1)


def test_project_to_so3_properties():
    R = haar_rotations(100, seed=12)
    # idempotent on rotations
    torch.testing.assert_close(project_to_so3(R), R, atol=1e-12, rtol=0)
    # noisy rotations: output is a rotation, near the clean one, and matches the polar factor
    noise = 0.05 * torch.randn(100, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(13))
    M = R + noise
    P = project_to_so3(M)
    assert_is_rotation(P)
    torch.testing.assert_close(project_to_so3(P), P, atol=1e-12, rtol=0)
    # independent reference: for det(M) > 0 the nearest rotation is the orthogonal polar factor
    # M (M^T M)^{-1/2}, computed with scipy
    from scipy.linalg import sqrtm

    for i in range(10):
        Mi = M[i].numpy()
        assert np.linalg.det(Mi) > 0
        polar = Mi @ np.linalg.inv(np.real(sqrtm(Mi.T @ Mi)))
        np.testing.assert_allclose(P[i].numpy(), polar, atol=1e-10)
    # closer (Frobenius) than the clean rotation and many random rotations
    dist = (P - M).flatten(1).norm(dim=1)
    assert torch.all(dist <= (R - M).flatten(1).norm(dim=1) + 1e-12)
    others = haar_rotations(500, seed=14)
    for i in range(10):
        assert dist[i] <= (others - M[i]).flatten(1).norm(dim=1).min()


def test_project_to_so3_negative_determinant_and_scipy_align():
    g = torch.Generator().manual_seed(15)
    M = torch.randn(200, 3, 3, dtype=torch.float64, generator=g)
    P = project_to_so3(M)
    assert_is_rotation(P)
    neg = torch.linalg.det(M) < 0
    assert neg.any() and (~neg).any()
    # a reflection projects to a rotation, e.g. diag(1, 1, -1) -> some rotation with det +1
    Pr = project_to_so3(torch.diag(torch.tensor([1.0, 2.0, -3.0], dtype=torch.float64)))
    assert torch.linalg.det(Pr).item() == pytest.approx(1.0, abs=1e-12)
    # The projection maximises tr(P^T M) over SO(3): it beats 2000 random rotations, and equals
    # scipy's solution of Wahba's problem.
    cands = haar_rotations(2000, seed=16)
    for i in range(20):
        obj = (P[i] * M[i]).sum()
        assert obj >= (cands * M[i]).sum(dim=(-1, -2)).max() - 1e-12
        # Wahba's problem: align_vectors finds R minimising sum |a_i - R b_i|^2, i.e. maximising
        # tr(R^T sum_i a_i b_i^T); with a_i = M e_i (columns) and b_i = e_i that is tr(R^T M).
        r, _ = Rotation.align_vectors(M[i].numpy().T, np.eye(3))
        np.testing.assert_allclose(P[i].numpy(), r.as_matrix(), atol=1e-8)
    with pytest.raises(ValueError):
        project_to_so3(torch.zeros(3, 2))


# ---------------------------------------------------------------------------------- random rotations
def test_random_rotations_valid_and_reproducible():
    R = random_rotations(1000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert R.shape == (1000, 3, 3) and R.dtype == torch.float64
    assert_is_rotation(R)
    R2 = random_rotations(1000, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert torch.equal(R, R2)
    R3 = random_rotations(1000, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    assert not torch.allclose(R, R3)
    assert random_rotations(5, generator=torch.Generator().manual_seed(0)).dtype == torch.get_default_dtype()
    assert random_rotations(0).shape == (0, 3, 3)
    with pytest.raises(ValueError):
        random_rotations(-1)


def test_random_rotations_haar_statistics():
    n = 20000
    R = random_rotations(n, generator=torch.Generator().manual_seed(42), dtype=torch.float64)
    # E[R] = 0 under Haar; each entry has variance 1/3 -> std of the mean ~ 0.004
    assert R.mean(dim=0).abs().max() < 0.025
    # E[R_ij R_kl] = delta_ik delta_jl / 3
    second = torch.einsum("nij,nkl->ijkl", R, R) / n
    expected = torch.einsum("ik,jl->ijkl", torch.eye(3, dtype=torch.float64), torch.eye(3, dtype=torch.float64)) / 3
    assert (second - expected).abs().max() < 0.02
    # angle density (1 - cos t) / pi on [0, pi]: mean pi/2 + 2/pi, and CDF (t - sin t) / pi
    t = geodesic_distance(torch.eye(3, dtype=torch.float64), R)
    mean_expected = math.pi / 2 + 2 / math.pi
    # std of t under Haar is ~0.57 -> std of the mean ~0.004
    assert abs(t.mean().item() - mean_expected) < 0.02
    ts = np.sort(t.numpy())
    cdf = (ts - np.sin(ts)) / np.pi
    ks = np.max(np.abs(cdf - np.arange(1, n + 1) / n))
    assert ks < 1.6 / math.sqrt(n)  # Kolmogorov-Smirnov, alpha ~ 0.01


# ---------------------------------------------------------------------------------- rotation vectors
def test_rotvec_to_matrix_matches_scipy():
    g = np.random.default_rng(17)
    axes = g.normal(size=(100, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    angles = g.uniform(0, np.pi, size=(100, 1))
    rv = axes * angles
    rv[0] = 0.0
    rv[1] = [0, 0, np.pi]
    rv[2] = [1e-9, 0, 0]
    expected = Rotation.from_rotvec(rv).as_matrix()
    got = rotvec_to_matrix(torch.as_tensor(rv))
    np.testing.assert_allclose(got.numpy(), expected, atol=1e-12)
    assert rotvec_to_matrix(torch.as_tensor(rv).reshape(4, 25, 3)).shape == (4, 25, 3, 3)
    # the angle of exp(skew(v)) is |v|
    d = geodesic_distance(torch.eye(3, dtype=torch.float64), got[3:])
    torch.testing.assert_close(d, torch.as_tensor(angles[3:, 0]), atol=1e-7, rtol=0)
    with pytest.raises(ValueError):
        rotvec_to_matrix(torch.zeros(4))


def test_rotvec_to_matrix_gradient_at_zero():
    w = torch.zeros(3, dtype=torch.float64, requires_grad=True)
    R = rotvec_to_matrix(w)
    v = torch.tensor([0.2, -0.4, 0.9], dtype=torch.float64)
    (R @ v).sum().backward()
    # exp([w]_x) v = v + w x v + O(w^2), and sum(w x v) = w . (v x 1)
    expected = torch.cross(v, torch.ones(3, dtype=torch.float64), dim=0)
    torch.testing.assert_close(w.grad, expected, atol=1e-12, rtol=0)


def test_quaternion_to_matrix_rejects_integer_tensors():
    with pytest.raises(ValueError, match="floating point"):
        quaternion_to_matrix(torch.tensor([1, 0, 0, 0]), order="wxyz")


# ---------------------------------------------------------------------------------- the rest of the catalogue
@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_rotation_about_axis_matches_scipy(axis):
    t = torch.linspace(-7.0, 7.0, 101, dtype=torch.float64).reshape(1, 101)
    expected = Rotation.from_euler(axis, t[0].numpy()[:, None]).as_matrix()
    np.testing.assert_allclose(rotation_about_axis(axis, t)[0].numpy(), expected, atol=1e-15, rtol=0)
    with pytest.raises(ValueError, match="axis"):
        rotation_about_axis("w", t)


def test_aet_chart_is_scipy_xyz_with_negated_angles_and_round_trips():
    g = np.random.default_rng(3)
    a, e, t = g.uniform(-np.pi, np.pi, (3, 200))
    e = e / 2  # cos e >= 0: the preimage matrix_to_aet_biternions returns
    R = aet_to_matrix(*(torch.as_tensor(x) for x in (a, e, t)))
    expected = Rotation.from_euler("XYZ", np.stack([-t, -e, -a], 1)).as_matrix()
    np.testing.assert_allclose(R.numpy(), expected, atol=1e-14, rtol=0)
    ba, be, bt = matrix_to_aet_biternions(R)
    for b, x in ((ba, a), (be, e), (bt, t)):
        np.testing.assert_allclose(b.numpy(), np.stack([np.cos(x), np.sin(x)], 1), atol=1e-12, rtol=0)
    torch.testing.assert_close(aet_biternions_to_matrix(ba, be, bt), R, atol=1e-14, rtol=0)
    with pytest.raises(ValueError, match=r"azimuth \(2,\).*tilt \(3,\)"):
        aet_to_matrix(torch.zeros(2), torch.zeros(1), torch.zeros(3))
    with pytest.raises(ValueError, match=r"\(\.\.\., 2\), got \(3,\)"):
        aet_biternions_to_matrix(torch.zeros(3), torch.zeros(2), torch.zeros(2))


@pytest.mark.parametrize("order", ["wxyz", "xyzw"])
def test_matrix_to_quaternion_matches_scipy_and_round_trips(order):
    R = haar_rotations(300, seed=21)
    q = matrix_to_quaternion(R, order)
    ref = Rotation.from_matrix(R.numpy()).as_quat()  # xyzw
    ref = ref * np.where(ref[:, 3:] < 0, -1.0, 1.0)  # w >= 0
    np.testing.assert_allclose(q.numpy(), ref if order == "xyzw" else ref[:, [3, 0, 1, 2]], atol=1e-12, rtol=0)
    torch.testing.assert_close(quaternion_to_matrix(q, order), R, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="order"):
        matrix_to_quaternion(R, "wzyx")
    with pytest.raises(ValueError, match=r"\(\.\.\., 3, 3\), got \(4, 4\)"):
        matrix_to_quaternion(torch.eye(4), order)


def test_quaternion_multiply_composes_rotations():
    p, q = (torch.as_tensor(Rotation.random(50, random_state=s).as_quat()[:, [3, 0, 1, 2]]) for s in (1, 2))
    R = quaternion_to_matrix(quaternion_multiply(p, q), "wxyz")
    torch.testing.assert_close(R, quaternion_to_matrix(p, "wxyz") @ quaternion_to_matrix(q, "wxyz"))
    with pytest.raises(ValueError, match=r"p \(50, 4\), q \(3, 4\)"):
        quaternion_multiply(p, q[:3])


def test_proper_svd_has_rotation_factors_and_signed_last_value():
    M = torch.randn(100, 3, 3, dtype=torch.float64, generator=torch.Generator().manual_seed(4))
    U, s, V = proper_svd(M)
    assert_is_rotation(U)
    assert_is_rotation(V)
    torch.testing.assert_close(U @ torch.diag_embed(s) @ V.transpose(-1, -2), M)
    assert ((s[:, 0] >= s[:, 1]) & (s[:, 1] >= s[:, 2].abs())).all()
    assert torch.equal(s[:, 2] < 0, torch.linalg.det(M) < 0)
    torch.testing.assert_close(project_to_so3(M), U @ V.transpose(-1, -2))
    with pytest.raises(ValueError, match=r"\(3, 2\)"):
        proper_svd(torch.zeros(3, 2))


@pytest.mark.parametrize("name", ["T", "O", "I", "C4", "D3"])
def test_rotation_group_is_scipys_group_identity_first(name):
    scipy_group = Rotation.create_group(name).as_matrix()
    for sort in (False, True):
        G = rotation_group(name, sort=sort)
        assert G.dtype == torch.float64 and G.shape == scipy_group.shape
        assert torch.equal(G[0], torch.eye(3, dtype=torch.float64))
        # the same elements as scipy's, each once
        diff = (G[:, None].numpy() - scipy_group[None]).reshape(len(G), len(G), 9)
        match = np.abs(diff).max(-1) < 1e-9
        assert (match.sum(0) == 1).all() and (match.sum(1) == 1).all()
        order = np.argmax(match, axis=1)[1:]  # where each non-identity element sits in scipy's order
        if sort:
            keys = [tuple(np.round(g, 9).ravel()) for g in G[1:].numpy()]
            assert keys == sorted(keys)
        else:
            assert (np.diff(order) > 0).all()
    if name in ("T", "O"):
        assert torch.equal(G, G.round())  # snapped to exact 0 and +-1
    G[0, 0, 0] = 5.0  # a fresh tensor each call
    assert rotation_group(name)[0, 0, 0] == 1.0
    with pytest.raises(ValueError, match="'X'"):
        rotation_group("X")
