"""The SO(3) distribution plot and the mode finder, on distributions with known peaks."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy.spatial.transform import Rotation

from conftest import haar_rotations
from image2sphere.distributions import SO3Distribution
from image2sphere.plot import plot_so3_distribution, rotation_to_plot_coords, save_figure
from image2sphere.so3 import dense_grid_logits, so3_grid_size
from image2sphere.so3.rotations import geodesic_distance_deg
from image2sphere.so3.wigner import flat_wigner

LMAX = 6


def peaks_at(R: torch.Tensor, scale: float) -> SO3Distribution:
    """``f(R) = scale * sum_k sum_l (2l+1) chi_l(R_k^T R)``: a band-limited peak at every ``R_k``."""
    coeffs = scale * flat_wigner(LMAX, R.double()).sum(0, keepdim=True) / len(R)
    return SO3Distribution(coeffs, LMAX)


def test_plot_coordinates_are_xyx_euler_angles():
    R = haar_rotations(50, seed=3).numpy()
    lon, lat, hue = rotation_to_plot_coords(R)
    alpha, beta, gamma = Rotation.from_matrix(R).as_euler("XYX").T  # intrinsic: Rx(a) Ry(b) Rx(g)
    np.testing.assert_allclose(lon, alpha, atol=1e-9)
    np.testing.assert_allclose(lat, np.pi / 2 - beta, atol=1e-9)
    np.testing.assert_allclose(hue, np.mod(gamma, 2 * np.pi) / (2 * np.pi), atol=1e-9)
    with pytest.raises(ValueError, match=r"got \(3,\)"):
        rotation_to_plot_coords(np.zeros(3))


@pytest.mark.parametrize("level", [2])
def test_points_above_threshold_match_the_dense_grid(level):
    dist = peaks_at(haar_rotations(3, seed=1), scale=0.05)
    p = torch.softmax(dense_grid_logits(dist.coeffs, LMAX, level), -1)[0]
    threshold = 3.0 / p.numel()
    index, prob = dist.points_above(threshold, level)[0]
    expected = torch.nonzero(p >= threshold).flatten()
    assert 0 < len(expected) < p.numel() // 4
    assert sorted(index.tolist()) == sorted(expected.tolist())
    torch.testing.assert_close(prob, p[index], rtol=1e-6, atol=1e-12)
    assert (prob[:-1] >= prob[1:]).all()  # most probable first
    with pytest.raises(ValueError, match="threshold must be > 0"):
        dist.points_above(0.0, level)


def test_plot_draws_exactly_the_points_above_the_threshold_and_the_gt_rings(tmp_path):
    gt = haar_rotations(4, seed=2)
    dist = peaks_at(gt, scale=0.05)
    level = 2
    p = torch.softmax(dense_grid_logits(dist.coeffs, LMAX, level), -1)[0]
    threshold = 5.0 / p.numel()
    fig = plot_so3_distribution(dist, level=level, threshold=threshold, gt_rotations=gt, title="four peaks")
    points, rings = fig.axes[0].collections[:2]
    assert len(points.get_offsets()) == int((p >= threshold).sum()) > 0
    np.testing.assert_allclose(np.asarray(rings.get_offsets()), np.stack(rotation_to_plot_coords(gt)[:2], 1))
    sizes = points.get_sizes()
    assert sizes.max() == pytest.approx(60.0) and sizes.min() < sizes.max()  # area proportional to p
    path = save_figure(fig, tmp_path / "plot.png")
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    with pytest.raises(FileExistsError):
        save_figure(fig, path)
    with pytest.raises(ValueError, match="batch of 1"):
        plot_so3_distribution(SO3Distribution(dist.coeffs.expand(2, -1), LMAX))


def test_modes_of_the_cube_group_are_its_24_rotations():
    """A distribution peaked at the 24 rotations of a cube's orientation: 24 modes, equal mass."""
    R0 = haar_rotations(1, seed=5)[0]
    group = torch.as_tensor(Rotation.create_group("O").as_matrix())
    targets = R0 @ group
    dist = peaks_at(targets, scale=0.5)  # peaks a few grid steps wide
    rotations, mass = dist.modes(level=3, k=40, radius_deg=30.0)[0]
    assert len(rotations) == 24
    spacing = 360.0 / so3_grid_size(3)[1]
    # every mode is within a grid step of a distinct group element
    d = geodesic_distance_deg(rotations[:, None], targets[None])  # [24, 24]
    assert (d.min(1).values < 2 * spacing).all() and len(set(d.argmin(1).tolist())) == 24
    # equal peaks, equal masses (the grid samples each peak a little differently)
    assert mass.sum() > 0.8 and (mass.max() - mass.min()) < 0.05 * mass.mean()
    # refined modes move off the grid, closer to the true peaks
    refined, _ = dist.modes(level=3, k=40, radius_deg=30.0, refine=True)[0]
    d_refined = geodesic_distance_deg(refined[:, None], targets[None]).min(1).values
    assert d_refined.mean() < d.min(1).values.mean()
    # k limits the number; a single peak gives one mode holding most of the mass
    assert len(dist.modes(level=3, k=5, radius_deg=30.0)[0][0]) == 5
    one, one_mass = peaks_at(targets[:1], scale=0.5).modes(level=3, k=5, radius_deg=30.0)[0]
    assert len(one) == 1 and one_mass[0] > 0.8
    assert math.isclose(geodesic_distance_deg(one[0], targets[0]).item(), 0.0, abs_tol=2 * spacing)
