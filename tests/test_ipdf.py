"""Implicit-PDF (:class:`image2sphere.nn.ipdf.IPDF`) and :class:`ImplicitDistribution`.

Tiny stand-ins (a one-layer conv encoder, a narrow MLP) keep the file fast; the reference grid
densities are computed here from the module's weights, not through its scoring code.
"""

from __future__ import annotations

import math

import pytest
import torch
from torch import nn

import image2sphere.distributions.grid_protocol as base
import image2sphere.distributions.implicit as implicit
from image2sphere.distributions.implicit import ImplicitDistribution
from image2sphere.nn.ipdf import IPDF, positional_encoding
from image2sphere.so3.grid import so3_grid_size, so3_healpix_grid
from image2sphere.so3.rotations import random_rotations

LOG_PI2 = math.log(math.pi**2)


class TinyEncoder(nn.Module):
    """A conv stand-in for the ResNet: ``[B, 3, H, W]`` -> ``[B, 6, H/2, W/2]``."""

    out_channels = 6

    def __init__(self):
        super().__init__()
        self.conv = nn.Conv2d(3, self.out_channels, 3, stride=2, padding=1)

    def forward(self, images):
        return torch.relu(self.conv(images))


def tiny_ipdf(**kwargs) -> IPDF:
    options = dict(hidden=16, depth=2, num_fourier=2, n_queries=128) | kwargs
    return IPDF(TinyEncoder(), image_size=16, **options)


@pytest.fixture(autouse=True)
def _seed_and_one_thread():
    previous = torch.get_num_threads()
    torch.set_num_threads(1)
    torch.manual_seed(0)
    try:
        yield
    finally:
        torch.set_num_threads(previous)


def reference_logits(model: IPDF, features: torch.Tensor, rotations: torch.Tensor) -> torch.Tensor:
    """``(B, N)`` scores at shared rotations ``(N, 3, 3)`` from the weights, written out independently."""
    v = rotations.reshape(-1, 9)  # [N, 9]
    enc = []
    for k in range(model.num_fourier):
        enc += [torch.sin(v * 2**k), torch.cos(v * 2**k)]
    q = torch.cat(enc, dim=1) if enc else v  # [N, 18 L]
    h = features @ model.feature_proj.weight.T + model.feature_proj.bias  # [B, W]
    h = torch.relu(h[:, None, :] + q @ model.query_proj.weight.T)  # [B, N, W]
    for layer in model.layers:
        h = layer(h) if not isinstance(layer, nn.Linear) else h @ layer.weight.T + layer.bias
    return (h @ model.head.weight.T + model.head.bias)[..., 0]  # [B, N]


def test_shapes_and_bad_input():
    model = tiny_ipdf()
    images = torch.randn(5, 3, 16, 16)
    features = model(images)
    assert features.shape == (5, 6)
    dist = model.output_distribution(features)
    assert dist.batch_size == 5 and dist.dtype == torch.float32
    assert dist.unnormalized_log_density(random_rotations(7)).shape == (5, 7)
    assert dist.unnormalized_log_density(random_rotations(35).reshape(5, 7, 3, 3)).shape == (5, 7)
    assert model.loss(features, random_rotations(5), grid_level=2).shape == (5,)
    assert positional_encoding(torch.zeros(4, 9), 3).shape == (4, 54)
    assert model.score(features, random_rotations(3)).shape == (5, 3)

    with_class = tiny_ipdf(num_classes=4)
    out = with_class(images, torch.tensor([0, 1, 2, 3, 0]))
    assert out.shape == (5, 10) and torch.equal(out[:, 6:].argmax(1), torch.tensor([0, 1, 2, 3, 0]))

    with pytest.raises(ValueError, match=r"\(2, 5, 3, 3\)"):
        dist.unnormalized_log_density(torch.eye(3).expand(2, 5, 3, 3))
    with pytest.raises(ValueError, match=r"\(7, 3\)"):
        dist.unnormalized_log_density(torch.zeros(7, 3))
    with pytest.raises(ValueError, match=r"\(5, 4\)"):
        model.output_distribution(torch.zeros(5, 4))
    with pytest.raises(ValueError, match=r"\(4, 3, 3\)"):
        model.loss(features, random_rotations(4))
    with pytest.raises(ValueError, match="class_index"):
        with_class(images)
    with pytest.raises(ValueError, match="query_sampling"):
        tiny_ipdf(query_sampling="sobol")


def test_grid_density_is_normalised_and_matches_dense_softmax():
    model = tiny_ipdf(depth=3)
    features = torch.randn(3, 6, dtype=torch.float64) * 3
    model = model.double()
    dist = model.output_distribution(features)
    with torch.no_grad():
        log_p = dist.log_prob_grid(2)  # [B, N]
        grid = so3_healpix_grid(2, dtype=torch.float64)
        expected = torch.log_softmax(reference_logits(model, features, grid), dim=1)
        n = math.prod(so3_grid_size(2))
        assert log_p.shape == (3, n)
        torch.testing.assert_close(log_p.exp().sum(1), torch.ones(3, dtype=torch.float64), rtol=0, atol=1e-12)
        torch.testing.assert_close(log_p, expected, rtol=0, atol=1e-10)
        # the not-uniform part matters: the untrained density is not flat
        assert (expected.max(1).values - expected.min(1).values > 0.1).all()
        # density at grid points by the grid protocol: log(p_i * N / pi^2)
        index = torch.tensor([0, 17, 4000])
        got = dist.log_density(grid[index], level=2)
        torch.testing.assert_close(got, expected[:, index] + math.log(n) - LOG_PI2, rtol=0, atol=1e-9)


def test_loss_matches_formula_and_uniform_value():
    model = tiny_ipdf()
    features, rotation = torch.randn(4, 6), random_rotations(4)
    torch.manual_seed(3)
    loss = model.loss(features, rotation)
    torch.manual_seed(3)
    queries = model.train_queries()
    logits = torch.cat([model.score(features, rotation[:, None]), model.score(features, queries)], dim=1)
    density = torch.softmax(logits, dim=1)[:, 0] * (model.n_queries + 1) / math.pi**2
    torch.testing.assert_close(loss, -density.log(), rtol=1e-5, atol=1e-5)
    # a constant score is the uniform density: loss = log(pi^2)
    flat = ImplicitDistribution(features, lambda f, r: f.new_zeros(len(f), r.shape[-3]))
    model.output_distribution = lambda f: flat
    torch.testing.assert_close(model.loss(features, rotation), torch.full((4,), LOG_PI2))
    # grid queries: the level-2 grid (closest to 4096) under a random rotation
    grid_model = tiny_ipdf(query_sampling="grid", n_queries=4096)
    queries = grid_model.train_queries(torch.float64)
    assert queries.shape == (4608, 3, 3)
    torch.testing.assert_close(queries.transpose(1, 2) @ queries, torch.eye(3, dtype=torch.float64).expand_as(queries))


def test_loss_decreases_when_overfitting():
    model = tiny_ipdf(hidden=32, depth=2, num_fourier=2, n_queries=256)
    images, rotations = torch.randn(8, 3, 16, 16), random_rotations(8)
    optimizer = torch.optim.Adam(model.parameters(), lr=1e-2)
    losses = []
    for _ in range(100):
        loss = model.loss(model(images), rotations).mean()
        optimizer.zero_grad()
        loss.backward()
        optimizer.step()
        losses.append(loss.item())
    first, last = losses[0], sum(losses[-5:]) / 5
    assert first == pytest.approx(LOG_PI2, abs=0.3)  # near-uniform at initialisation
    assert last < first - 1.5, (first, last)
    with torch.no_grad():  # the grid protocol agrees: the true rotations are more likely than uniform
        log_density = model.output_distribution(model(images)).log_density(rotations[:, None], level=2)[:, 0]
    assert (log_density > -LOG_PI2 + 1.0).all(), log_density


def test_scoring_is_per_image():
    model = tiny_ipdf()
    images = torch.randn(6, 3, 16, 16)
    perm = torch.tensor([3, 0, 5, 1, 4, 2])
    features = model(images)
    torch.testing.assert_close(model(images[perm]), features[perm])
    shared, own = random_rotations(9), random_rotations(54).reshape(6, 9, 3, 3)
    dist, permuted = model.output_distribution(features), model.output_distribution(features[perm])
    torch.testing.assert_close(permuted.unnormalized_log_density(shared), dist.unnormalized_log_density(shared)[perm])
    torch.testing.assert_close(permuted.unnormalized_log_density(own[perm]), dist.unnormalized_log_density(own)[perm])
    # per-image rotations equal the shared ones where they coincide
    torch.testing.assert_close(
        dist.unnormalized_log_density(shared.expand(6, 9, 3, 3)), dist.unnormalized_log_density(shared)
    )


def test_level4_grid_is_swept_in_chunks(monkeypatch):
    model = tiny_ipdf()
    features = torch.randn(4, 6)
    level, n = 4, math.prod(so3_grid_size(4))
    with torch.no_grad():
        dense = model.output_distribution(features).grid_log_density(level)  # [B, N]: the reference
        calls = []
        score = model.score

        def recording_score(f, r):
            calls.append(r.shape[-3])
            return score(f, r)

        monkeypatch.setattr(base, "CHUNK_POINTS", 40_000)
        monkeypatch.setattr(implicit, "MAX_ACTIVATION_ELEMENTS", 4 * 16 * 5_000)  # B * width * 5000 points
        dist = ImplicitDistribution(features, recording_score, width=model.hidden)
        lse, top, arg = dist.grid_logsumexp_and_max(level)
    # chunks of whole groups of fibres (768 points at level 4): 39,936 points, 7 full chunks of 8 sub-calls,
    # then 15,360 points in 4
    assert sum(calls) == n and max(calls) == 5_000 and len(calls) == 7 * 8 + 4
    torch.testing.assert_close(lse, torch.logsumexp(dense, dim=1))
    torch.testing.assert_close(top, dense.max(dim=1).values)
    assert torch.equal(arg, dense.argmax(dim=1))


def test_distribution_of_images_is_the_output_distribution_of_their_features():
    """Quick. ``IPDF.distribution(images)`` is ``output_distribution(net(images))``: the same scores."""
    model = tiny_ipdf().eval()
    images, R = torch.randn(2, 3, 16, 16), random_rotations(4)
    with torch.no_grad():
        direct = model.distribution(images).unnormalized_log_density(R)
        via = model.output_distribution(model(images)).unnormalized_log_density(R)
    torch.testing.assert_close(direct, via, rtol=0, atol=0)
