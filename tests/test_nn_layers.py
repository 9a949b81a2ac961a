"""Equivariance and closed forms of the S2/SO(3) layers."""

import math

import pytest
import torch
from e3nn import o3

from image2sphere.nn import S2Conv, SO3Conv, SO3ReLU
from image2sphere.so3 import (
    flat_wigner,
    geodesic_distance,
    n_s2_coeffs,
    n_so3_coeffs,
    random_rotations,
    s2_healpix_grid,
    so3_near_identity_grid,
)
from image2sphere.testing import assert_left_equivariant, equivariance_error

LMAX = 6


@pytest.fixture
def gen():
    return torch.Generator().manual_seed(1234)


@pytest.mark.parametrize("filter", ["harmonic", "spatial"])
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_s2_conv_is_left_equivariant(filter, dtype, gen):
    torch.manual_seed(0)
    conv = S2Conv(4, 3, LMAX, filter=filter).to(dtype)
    x = torch.randn(2, 4, n_s2_coeffs(LMAX), dtype=dtype, generator=gen)
    assert_left_equivariant(conv, x, LMAX, "s2", generator=gen)


@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_so3_conv_is_left_equivariant(dtype, gen):
    torch.manual_seed(0)
    conv = SO3Conv(3, 2, LMAX).to(dtype)
    x = torch.randn(2, 3, n_so3_coeffs(LMAX), dtype=dtype, generator=gen)
    assert_left_equivariant(conv, x, LMAX, "so3", generator=gen)


def test_head_is_left_equivariant_up_to_activation_grid_error(gen):
    torch.manual_seed(0)
    head = torch.nn.Sequential(S2Conv(5, 4, LMAX), SO3ReLU(LMAX, resolution=8), SO3Conv(4, 1, LMAX)).double()
    x = torch.randn(2, 5, n_s2_coeffs(LMAX), dtype=torch.float64, generator=gen)
    # the ReLU is evaluated on e3nn's finite SO(3) grid: equivariant only up to its sampling error
    assert_left_equivariant(head, x, LMAX, "s2", rtol=2e-2, generator=gen)
    linear = torch.nn.Sequential(S2Conv(5, 4, LMAX), SO3Conv(4, 1, LMAX)).double()
    assert_left_equivariant(linear, x, LMAX, "s2", generator=gen)


def test_so3_relu_error_shrinks_with_resolution(gen):
    x = torch.randn(2, 3, n_so3_coeffs(LMAX), dtype=torch.float64, generator=gen)
    R = random_rotations(1, generator=gen, dtype=torch.float64)[0]
    coarse = equivariance_error(SO3ReLU(LMAX, 4).double(), x, LMAX, "so3", R)
    fine = equivariance_error(SO3ReLU(LMAX, 10).double(), x, LMAX, "so3", R)
    assert fine < coarse and fine < 5e-3


class _TransposedS2Conv(S2Conv):
    """The S2 convolution with input and filter indices swapped (i.e. D transposed): not left-equivariant."""

    def forward(self, x):
        xs = x[..., self.index_psi]
        ps = self.filter()[..., self.index_x]
        return torch.einsum("bfi,fgi->bgi", xs, ps) / math.sqrt(self.in_channels)


def test_equivariance_check_catches_a_broken_convention(gen):
    conv = _TransposedS2Conv(3, 2, LMAX).double()
    x = torch.randn(2, 3, n_s2_coeffs(LMAX), dtype=torch.float64, generator=gen)
    with pytest.raises(AssertionError, match="not left-equivariant"):
        assert_left_equivariant(conv, x, LMAX, "s2", generator=gen)


def test_s2_conv_equals_the_spatial_group_convolution(gen):
    """out(g) = integral of x(u) psi'(g^-1 u) du / 4 pi, with psi'^l = sqrt(2l+1) psi^l: checked by quadrature."""
    lmax = 2
    conv = S2Conv(1, 1, lmax).double()
    x = torch.randn(1, 1, n_s2_coeffs(lmax), dtype=torch.float64, generator=gen)
    scale = torch.cat([torch.full((2 * l + 1,), math.sqrt(2 * l + 1)) for l in range(lmax + 1)]).double()
    psi = conv.weight[0, 0].detach() * scale  # [(lmax+1)^2]
    out = conv(x)[0, 0].detach()
    alpha, beta = s2_healpix_grid(6, dtype=torch.float64)  # 49152 equal-area points
    u = o3.angles_to_xyz(alpha, beta)  # [P, 3]
    Y = o3.spherical_harmonics(list(range(lmax + 1)), u, normalize=True, normalization="component")
    for g in random_rotations(3, generator=gen, dtype=torch.float64):
        Yrot = o3.spherical_harmonics(list(range(lmax + 1)), u @ g, normalize=True, normalization="component")
        integral = ((Y @ x[0, 0]) * (Yrot @ psi)).mean()  # u @ g = g^T u = g^-1 u
        fourier = flat_wigner(lmax, g) @ out
        assert fourier.item() == pytest.approx(integral.item(), abs=2e-3 * float(x.abs().max() * psi.abs().max()))


def test_so3_conv_with_one_kernel_point_is_right_translation(gen):
    g = random_rotations(1, generator=gen, dtype=torch.float64)
    conv = SO3Conv(1, 1, lmax=4, kernel=g).double()
    with torch.no_grad():
        conv.weight.fill_(1.0)
    f = torch.randn(1, 1, n_so3_coeffs(4), dtype=torch.float64, generator=gen)
    out = conv(f)[0, 0]
    R = random_rotations(6, generator=gen, dtype=torch.float64)
    expected = flat_wigner(4, R @ g[0]) @ f[0, 0]  # f(R g)
    torch.testing.assert_close(flat_wigner(4, R) @ out, expected, atol=1e-5, rtol=1e-5)


def test_so3_conv_filter_is_locally_supported():
    max_angle = math.radians(22.5)
    kernel = so3_near_identity_grid(max_angle, dtype=torch.float64)
    angles = geodesic_distance(kernel, torch.eye(3, dtype=torch.float64))
    assert angles.max() <= max_angle + 1e-9
    assert angles.max() >= max_angle - 1e-9 and angles.min() == 0


@pytest.mark.parametrize("out_channels", [1, 3])
def test_each_weights_gradient_has_the_weights_strides(out_channels, gen):
    """DDP's reducer copies (and warns about) a gradient whose strides differ from its parameter's; the last
    SO(3) convolution of I2S has one output channel, a size-1 dimension that an einsum gives another stride.
    The filter equals the einsum it replaces."""
    layers = torch.nn.Sequential(S2Conv(5, 4, LMAX), SO3ReLU(LMAX, resolution=8), SO3Conv(4, out_channels, LMAX))
    x = torch.randn(2, 5, (LMAX + 1) ** 2, generator=gen)
    layers(x).square().sum().backward()
    for name, p in layers.named_parameters():
        assert p.grad.stride() == p.stride(), name
    conv = layers[2]
    torch.testing.assert_close(conv.filter(), torch.einsum("fgk,kn->fgn", conv.weight, conv.kernel_D))


def test_layers_reject_bad_shapes():
    with pytest.raises(ValueError, match="S2 input must have shape"):
        S2Conv(4, 2, LMAX)(torch.randn(2, 4, 50))
    with pytest.raises(ValueError, match="SO\\(3\\) input must have shape"):
        SO3Conv(2, 2, LMAX)(torch.randn(2, 3, 455))
    with pytest.raises(ValueError, match="filter must be one of"):
        S2Conv(4, 2, LMAX, filter="fourier")
    with pytest.raises(ValueError, match="lmax"):
        S2Conv(4, 2, -1)
    with pytest.raises(ValueError, match="resolution"):
        SO3ReLU(LMAX, 0)
    with pytest.raises(ValueError, match="resolution"):
        SO3ReLU(LMAX, 8.5)


def test_relu_grid_follows_the_band_limit_and_keeps_its_aliasing_bounded():
    """Quick (about 6 s). The ReLU's grid is ``max(8, lmax + 2)`` by default. Why ``lmax + 2``, checked
    against e3nn's ReLU on a dense grid (resolution ``2 lmax + 4``) at lmax 2 to 4, where that is cheap:
    with ``lmax + 2`` the aliasing stays at the same few 1e-3 at every band limit (measured 4.2e-3, 4.6e-3,
    5.9e-3), about half that of a grid one degree coarser, while a grid fixed at one resolution (4 here,
    as 8 was fixed for every lmax) falls behind as lmax grows (2.3e-2 at lmax 4)."""
    from e3nn.nn import SO3Activation

    from image2sphere.nn.activation import default_relu_resolution
    from image2sphere.so3.wigner import default_dtype

    assert [default_relu_resolution(lmax) for lmax in (0, 2, 6, 7, 8, 10)] == [8, 8, 8, 9, 10, 12]
    assert SO3ReLU(2).resolution == 8 and SO3ReLU(2, None).resolution == 8 and SO3ReLU(2, 3).resolution == 3
    x_gen = torch.Generator().manual_seed(0)
    errors = {}
    with default_dtype(torch.float64):
        for lmax in (2, 3, 4):
            x = torch.randn(8, n_so3_coeffs(lmax), generator=x_gen, dtype=torch.float64)
            dense = SO3Activation(lmax, lmax, torch.relu, 2 * lmax + 4)(x)
            for res in {lmax + 1, lmax + 2, 4}:
                errors[lmax, res] = float((SO3ReLU(lmax, res)(x) - dense).norm() / dense.norm())
    for lmax in (2, 3, 4):
        assert errors[lmax, lmax + 2] < 7e-3, errors
        assert errors[lmax, lmax + 2] < 0.7 * errors[lmax, lmax + 1], errors
    assert errors[4, 4] > 3 * errors[4, 6], errors  # a fixed grid falls behind as lmax grows


def test_activation_buffers_are_not_saved():
    act = SO3ReLU(2, 4)
    assert act.state_dict() == {}
    assert len(list(act.buffers())) > 0


@pytest.mark.parametrize(("lmax", "resolution"), [(2, 3), (4, 6), (6, 8), (2, 1), (3, 1), (4, 2)])
def test_relu_computes_as_e3nns_own_on_fine_and_coarse_grids(lmax, resolution):
    """Quick. The separable grid against a freshly built e3nn ``SO3Activation`` (its dense Wigner matrices),
    in float64, values and gradients: on the default grids and on grids too coarse for the band limit, where
    e3nn's grid aliases the high frequencies (our Fourier basis then spans every function of its angles)."""
    from e3nn.nn import SO3Activation

    from image2sphere.so3.wigner import default_dtype

    with default_dtype(torch.float64):
        ours, reference = SO3ReLU(lmax, resolution), SO3Activation(lmax, lmax, torch.relu, resolution)
    x = torch.randn(3, 2, n_so3_coeffs(lmax), dtype=torch.float64, generator=torch.Generator().manual_seed(lmax))
    x.requires_grad_(True)
    weight = torch.randn(3, 2, n_so3_coeffs(lmax), dtype=torch.float64)
    (grad,) = torch.autograd.grad((ours(x) * weight).sum(), x)
    (expected_grad,) = torch.autograd.grad((reference(x) * weight).sum(), x)
    torch.testing.assert_close(ours(x), reference(x), rtol=0, atol=1e-12)
    torch.testing.assert_close(grad, expected_grad, rtol=0, atol=1e-12)
    # the grid itself: every point of e3nn's [alpha, beta, gamma] grid, ours laid out [beta, gamma, alpha]
    with torch.no_grad():
        grid = ours.to_grid(x).permute(0, 1, 4, 2, 3)
        torch.testing.assert_close(grid, reference.grid_in.to_grid(x), rtol=0, atol=1e-12)


def test_relu_layers_share_the_grid_built_once_and_keep_it_small(gen):
    """Quick. The grid's operator is built once per (lmax, resolution, dtype) and shared by every layer; each
    layer is still its own module (moving one leaves the others). It keeps the nonzero entries of the Wigner
    matrices in the grid's Fourier basis only: at lmax 6 and resolution 8, under 1 % of e3nn's dense
    ``[A, B, C, n]`` matrices. In float32 it agrees with e3nn's float32 module to e3nn's own rounding (its
    float32 Wigner matrices carry errors of 1e-5 to 1e-4)."""
    from e3nn.nn import SO3Activation

    from image2sphere.so3.wigner import default_dtype

    a, b = SO3ReLU(2, 3), SO3ReLU(2, 3)
    assert a is not b and a.values is b.values and a.indices is b.indices
    b.to(torch.float64)
    assert b.values.dtype == torch.float64 and a.values.dtype == torch.float32
    with default_dtype(torch.float64):
        c = SO3ReLU(2, 3)
    assert c.values.dtype == torch.float64
    x = torch.randn(4, n_so3_coeffs(2), generator=gen)
    torch.testing.assert_close(a(x), SO3Activation(2, 2, torch.relu, 3)(x), rtol=1e-4, atol=1e-4)
    six = SO3ReLU(6, 8)
    dense = 32 * 8**3 * n_so3_coeffs(6)  # e3nn's grid: 32 r^3 rotations
    assert six.values.numel() < 0.01 * dense, (six.values.numel(), dense)
