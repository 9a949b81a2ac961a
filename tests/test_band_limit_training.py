"""I2S learns at every band limit the paper's Table 7 varies (docs/training_fidelity.md, "The band limit").

At lmax 8 and 10 I2S used to stay at the uniform distribution. The cause: with the paper's random
subset of 20 projection points per training pass, the projection's Fourier coefficients are an
estimate whose sampling noise is white over the degrees while the feature map's signal is smooth,
so every degree above 2 is mostly noise, fresh at every step (noise/signal 32 at l = 6, 162 at
l = 10 on the built-in data, benchmarks/projection_noise.py); the more degrees, the more of the
logits are noise, and past lmax 6 the network learns to shrink its whole signal instead of
learning the pose. The default now projects on all points in training, as at test.

* quick: the default projection is deterministic in training (no sampling noise) and equals the
  test-time one; the paper's 20-point subset's noise grows with the degree past the signal.
* quick: why the cube stays uniform at lmax 2 in the fidelity matrix: a density invariant under the
  cube's 24 rotations has no Fourier component of degree 1, 2, 3 or 5 (the cubic harmonics).
* quick: why the icosahedron waits longest at uniform with one random equivalent label: only degree 6
  is invariant under its 60 rotations below degree 7, and 2.9 % of a label's gradient survives the
  average over the equivalent set (4.8 % for the cube, 9.3 % for the tetrahedron).
* slow: a short seeded training run at lmax 8 and at lmax 10 brings the training loss well below
  uniform's; with the 20-point subset (the code before the fix) it stays at uniform.
* slow: the Fourier MLP ("Fourier basis with MLP") learns once every degree takes an equal share of
  Adam's steps (``degree_power=1``, the default); with the coefficients as they come it stays near
  uniform (docs/training_fidelity.md, "The Fourier basis with an MLP").
"""

from __future__ import annotations

import math

import pytest
import torch
from hydra import compose, initialize
from hydra.utils import instantiate

from image2sphere.data.common import normalize_images
from image2sphere.data.raycast import render
from image2sphere.data.symmetry import symmetry_group
from image2sphere.nn.projector import SpatialS2Projector
from image2sphere.so3 import random_rotations
from image2sphere.so3.wigner import flat_wigner, so3_blocks

LEVEL = 3  # the training grid
LOG_N = math.log(72 * 8**LEVEL)  # uniform's loss: 10.51


def test_default_i2s_projects_on_all_points_in_training():
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", overrides=["lmax=8"])
    assert cfg.model.net.n_subset is None
    torch.manual_seed(0)
    proj = SpatialS2Projector(8, (3, 3), sphere_channels=4, lmax=8, n_subset=cfg.model.net.n_subset)
    features = torch.randn(2, 8, 3, 3)
    train = [proj.train()(features) for _ in range(2)]
    test = proj.eval()(features)
    torch.testing.assert_close(train[0], train[1], rtol=0, atol=0)  # nothing random in training
    torch.testing.assert_close(train[0], test)


def test_a_twenty_point_subset_is_mostly_noise_above_low_degrees():
    """The paper's subset: per degree, the mean square of (subset estimate - all points) against the
    all-points coefficients' own, on a smooth feature map (3x3, as 96 px images give)."""
    lmax = 10
    torch.manual_seed(0)
    proj = SpatialS2Projector(16, (3, 3), sphere_channels=32, lmax=lmax, n_subset=20)
    features = torch.randn(8, 16, 3, 3)
    with torch.no_grad():
        exact = proj.eval()(features)  # [B, S, (L+1)^2]
        noise = torch.stack([proj.train()(features) - exact for _ in range(32)])  # [T, B, S, (L+1)^2]
    ratio = []
    for l in range(lmax + 1):
        band = slice(l * l, (l + 1) ** 2)
        ratio.append(float(noise[..., band].pow(2).mean() / exact[..., band].pow(2).mean()))
    assert ratio[0] < 0.1 and ratio[1] < 1, ratio  # the low degrees are well estimated
    assert min(ratio[6:]) > 10, ratio  # from degree 6 on, the noise is 10x the signal or more
    assert ratio[10] > 3 * ratio[4], ratio  # and it grows with the degree


def test_cube_symmetric_densities_have_no_degree_1_2_3_or_5():
    """A density with f(R g) = f(R) for the cube's rotations g has, per degree l, (2l+1) x n_l free
    coefficients, n_l = the multiplicity of the trivial representation in D^l restricted to the group:
    (1/|G|) sum_g trace D^l(g), which for the octahedral group is 1, 0, 0, 0, 1, 0, 1, 0, 1, 1, 1 for
    l = 0..10 (one cubic harmonic at l = 4, 6, 8, 9, 10). At lmax 2 the only such density is uniform."""
    G = symmetry_group("cube").to(torch.float64)  # [24, 3, 3]
    D = flat_wigner(10, G)  # [24, n_so3], each block sqrt(2l+1) D^l
    multiplicity = []
    for l, block in so3_blocks(10):
        d = 2 * l + 1
        trace = D[:, block].unflatten(-1, (d, d)).diagonal(dim1=-2, dim2=-1).sum(-1) / math.sqrt(d)  # [24]
        multiplicity.append(float(trace.mean()))
    expected = [1, 0, 0, 0, 1, 0, 1, 0, 1, 1, 1]
    assert multiplicity == pytest.approx(expected, abs=1e-9)
    # and a group-averaged random signal keeps only those degrees
    coeffs = torch.randn(D.shape[-1], dtype=torch.float64)
    averaged = torch.zeros_like(coeffs)
    for l, block in so3_blocks(10):
        d = 2 * l + 1
        c = coeffs[block].view(d, d)
        Dg = D[:, block].unflatten(-1, (d, d)) / math.sqrt(d)  # [24, d, d]
        averaged[block] = (Dg @ c.T).mean(0).T.flatten()  # rows of c projected onto the invariant subspace
    norms = [float(averaged[block].norm()) for _, block in so3_blocks(10)]
    assert all((n > 1e-6) == bool(e) for n, e in zip(norms, expected, strict=True)), norms


def _trivial_multiplicities(G: torch.Tensor, lmax: int) -> list[float]:
    """Per degree l, (1/|G|) sum_g trace D^l(g): how many independent G-invariant rows D^l has."""
    D = flat_wigner(lmax, G.to(torch.float64))  # [|G|, n_so3], each block sqrt(2l+1) D^l
    out = []
    for l, block in so3_blocks(lmax):
        d = 2 * l + 1
        out.append(float((D[:, block].unflatten(-1, (d, d)).diagonal(dim1=-2, dim2=-1).sum(-1) / math.sqrt(d)).mean()))
    return out


@pytest.mark.parametrize(
    ("shape", "expected", "share"),
    [
        ("icosa", [1, 0, 0, 0, 0, 0, 1], 13 / 454),  # the icosahedral group: nothing between 0 and 6
        ("cube", [1, 0, 0, 0, 1, 0, 1], (9 + 13) / 454),
        ("tet", [1, 0, 0, 1, 1, 0, 2], (7 + 9 + 26) / 454),
    ],
)
def test_a_random_equivalent_label_is_mostly_noise_for_the_icosahedron(shape, expected, share):
    """Why the icosahedron waits longest at uniform with one random equivalent label per image
    (docs/training_fidelity.md, "Every SYMSOL shape"). At the uniform start the loss's gradient with
    respect to the output's coefficients is the label's flat Wigner vector; averaged over the image's
    equivalent set it keeps only the group-invariant rows (the multiplicities above, per degree), the
    rest is zero-mean noise from the draw. The share of its energy that survives, sum_l (2l+1) n_l /
    sum_l (2l+1)^2 over l = 1..6, is 2.9 % for the icosahedron (degree 6 alone), 4.8 % for the cube and
    9.3 % for the tetrahedron; the loss averaged over the set (dataset.label=all) has none of the noise."""
    G = symmetry_group(shape).to(torch.float64)
    assert _trivial_multiplicities(G, 6) == pytest.approx(expected, abs=1e-9)
    R = random_rotations(1, generator=torch.Generator().manual_seed(3), dtype=torch.float64)[0]
    labels = flat_wigner(6, R @ G)[:, 1:]  # [|G|, n_so3 - 1]: one label's gradient, degree 0 dropped
    signal = labels.mean(0)  # what every draw shares
    measured = float(signal.pow(2).sum() / labels.pow(2).sum(1).mean())
    assert measured == pytest.approx(share, rel=1e-9)


# ------------------------------------------------------------------ short training runs
SIZE = 48  # a 2x2 feature map
STEPS = 120


def _cone_images(n: int, seed: int) -> tuple[torch.Tensor, torch.Tensor]:
    g = torch.Generator().manual_seed(seed)
    rotations = random_rotations(n, generator=g, dtype=torch.float32)
    return normalize_images(render("cone", rotations, image_size=SIZE, supersample=1)), rotations


def _train_losses(
    overrides: list[str], images: torch.Tensor, rotations: torch.Tensor, steps: int = STEPS
) -> list[float]:
    """Losses of ``steps`` Adam steps (lr 1e-3, batches of 16) of the network that ``python -m src.train``
    builds with ``overrides`` (on 48 px images; I2S with 64 sphere channels)."""
    with initialize(version_base="1.3", config_path="../conf"):
        cfg = compose(config_name="train", overrides=[f"dataset.image_size={SIZE}", *overrides])
    if "sphere_channels" in cfg.model.net:
        cfg.model.net.sphere_channels = 64
    torch.manual_seed(0)
    net = instantiate(cfg.model.net)
    optimizer = instantiate(cfg.model.optimizer)(params=net.parameters())  # the run's: Adam, lr 1e-3, fused
    net.train()
    g = torch.Generator().manual_seed(1)
    losses = []
    for _ in range(steps):
        batch = torch.randint(len(images), (16,), generator=g)
        loss = net.loss(net(images[batch]), rotations[batch], LEVEL).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    return losses


def _late_loss(losses: list[float]) -> float:
    """The median of the last 20 steps' losses (one step of a sharp distribution can spike)."""
    return sorted(losses[-20:])[10]


# measured with one thread, as a test process of -n 2 has (median of the last 20 steps; uniform 10.51),
# with the run's fused Adam: all points at lmax 8: 9.40, 8.93, 7.92, 7.49, 7.27 after 40, 60, 80, 100, 120
# steps, so 100 steps leave 1.0 nats of margin; at lmax 10 (ReLU grid 12) 9.18, 8.52, 7.68, 7.15, 6.91, so
# 80 steps (two thirds of the cost of 120) still leave 0.8 nats of margin; the paper's 20-point subset
# 10.51 and 10.52 after 40 and 60 steps (stuck at uniform from step 20 on). The unfused Adam gave the same
# to 0.1 nats (7.58 at lmax 8 after 100 steps, 7.67 at lmax 10 after 80).
@pytest.mark.slow
@pytest.mark.parametrize(("lmax", "steps"), [(8, 100), (10, 80)])
def test_short_training_learns_at_high_band_limits(lmax, steps):
    images, rotations = _cone_images(256, seed=0)
    late = _late_loss(_train_losses([f"lmax={lmax}"], images, rotations, steps=steps))
    assert late < LOG_N - 2, f"lmax {lmax}: training loss {late:.2f}, uniform {LOG_N:.2f}"


@pytest.mark.slow
def test_short_training_with_the_twenty_point_subset_stays_uniform_at_lmax_8():
    """The same run with the paper's 20 random projection points per pass, a random last layer and the
    ReLU grid fixed at 8 (the code before the fixes)."""
    images, rotations = _cone_images(256, seed=0)
    before = ["lmax=8", "model.net.n_subset=20", "model.net.output_init=random", "model.net.activation_resolution=8"]
    late = _late_loss(_train_losses(before, images, rotations, steps=60))
    assert late > LOG_N - 0.3, f"lmax 8 with 20 points: training loss {late:.2f}, uniform {LOG_N:.2f}"


# ------------------------------------------------------------------ the Fourier basis with an MLP
# measured with one thread (median of the last 20 steps on 4096 cones; uniform 10.51) with the run's fused
# Adam, after 160, 200, 240 steps: degree_power 1 (the default) 8.73, 8.55, 8.22, degree_power 0 (the code
# before) 10.11, 10.02, 9.79, so 200 steps keep 0.45 nats of margin on both sides (the unfused Adam: 8.59
# and 9.99 at 200). On the built-in data the same two settings reach a test mean log likelihood of -0.85
# and -2.02 after 2 epochs.
@pytest.mark.slow
def test_fourier_mlp_learns_with_every_degree_given_an_equal_share_of_adams_steps():
    """The Fourier MLP's last layer gives the SO(3) coefficients; Adam moves every weight by about the
    same step, so with the coefficients as they come (``degree_power=0``) degree ``l`` takes a share
    ``(2l+1)^2`` of every change to the logits, mostly in high degrees whose gradient is noise, and the
    model stays near uniform. Scaling degree ``l`` by ``1 / (2l+1)`` (the default) lets it learn."""
    images, rotations = _cone_images(4096, seed=0)  # too many to memorise in 200 steps, as the built-in data
    runs = {
        p: _train_losses(["model=fourier_mlp", f"model.net.degree_power={p}"], images, rotations, steps=200)
        for p in (1, 0)
    }
    balanced, plain = _late_loss(runs[1]), _late_loss(runs[0])
    assert balanced < LOG_N - 1.5, f"degree_power 1: training loss {balanced:.2f}, uniform {LOG_N:.2f}"
    assert plain > LOG_N - 1.0, f"degree_power 0: training loss {plain:.2f}, uniform {LOG_N:.2f}"
