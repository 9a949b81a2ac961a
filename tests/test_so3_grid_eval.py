"""Tests for image2sphere.so3.grid_eval: the fast grid evaluator against dense evaluations."""

from __future__ import annotations

import pytest
import torch

from conftest import reference_dense_grid_logits, reference_flat_wigner
from image2sphere.so3 import (
    HealpixGridEvaluator,
    dense_grid_logits,
    flat_wigner,
    get_grid_evaluator,
    n_s2_coeffs,
    n_so3_coeffs,
    so3_grid_size,
    so3_healpix_grid,
)

LMAXES = [0, 1, 2, 4, 6]
LEVELS = [0, 1, 2, 3]


def random_coeffs(lmax: int, batch: int = 3, seed: int = 0, dtype=torch.float64) -> torch.Tensor:
    g = torch.Generator().manual_seed(1000 * lmax + seed)
    return torch.randn(batch, n_so3_coeffs(lmax), generator=g, dtype=torch.float64).to(dtype)


_dense_cache: dict[tuple[int, int], torch.Tensor] = {}


def dense(lmax: int, level: int) -> torch.Tensor:
    """float64 dense logits of ``random_coeffs(lmax)`` on the grid of ``level`` (cached)."""
    key = (lmax, level)
    if key not in _dense_cache:
        c = random_coeffs(lmax)
        # the package's own dense reference is slow beyond small grids; the two agree (tested above)
        if level <= 1 or lmax <= 1:
            _dense_cache[key] = dense_grid_logits(c, lmax, level)
        else:
            _dense_cache[key] = reference_dense_grid_logits(c, lmax, level)
    return _dense_cache[key]


# ---------------------------------------------------------------------------------- the dense references
@pytest.mark.parametrize(("lmax", "level"), [(0, 0), (2, 1), (6, 0), (4, 1)])
def test_dense_grid_logits_matches_e3nn_on_the_grid(lmax, level):
    """The package's dense reference equals flat e3nn Wigner rows of the grid rotations."""
    c = random_coeffs(lmax)
    G = so3_healpix_grid(level, dtype=torch.float64)
    sel = torch.arange(0, G.shape[0], 7)
    ref = c @ reference_flat_wigner(lmax, G[sel]).T
    got = dense_grid_logits(c, lmax, level)
    assert got.shape == (3, 72 * 8**level)
    torch.testing.assert_close(got[:, sel], ref, atol=1e-10, rtol=0)
    torch.testing.assert_close(got, reference_dense_grid_logits(c, lmax, level), atol=1e-10, rtol=0)


# ---------------------------------------------------------------------------------- full-grid logits
@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("lmax", LMAXES)
def test_logits_match_dense_float64(lmax, level):
    ev = get_grid_evaluator(lmax, level, torch.float64)
    c = random_coeffs(lmax)
    got = ev.logits(c)
    ref = dense(lmax, level)
    assert got.shape == (3, 72 * 8**level) and got.dtype == torch.float64
    scale = ref.abs().max()
    assert (got - ref).abs().max() <= 1e-9 * max(1.0, scale.item())
    assert ev.n_points == 72 * 8**level
    assert (ev.n_pix, ev.n_gamma) == so3_grid_size(level)


@pytest.mark.parametrize("level", LEVELS)
@pytest.mark.parametrize("lmax", LMAXES)
def test_logits_match_dense_float32(lmax, level):
    ev = get_grid_evaluator(lmax, level, torch.float32)
    got = ev.logits(random_coeffs(lmax, dtype=torch.float32))
    assert got.dtype == torch.float32
    ref = dense(lmax, level)
    assert (got.double() - ref).abs().max() <= 1e-4 * ref.abs().max()


@pytest.mark.slow
def test_logits_match_package_dense_level3_lmax6():
    c = random_coeffs(6, batch=2, seed=5)
    ref = dense_grid_logits(c, 6, 3)
    torch.testing.assert_close(get_grid_evaluator(6, 3, torch.float64).logits(c), ref, atol=1e-9, rtol=0)


def test_logits_of_delta_signal_peak_at_grid_point():
    """coeffs = flat_wigner(R0) for a grid rotation R0: the logits peak exactly there with value n_coeffs."""
    level, lmax = 2, 6
    G = so3_healpix_grid(level, dtype=torch.float64)
    idx = torch.tensor([0, 17, 1000, 1535])
    c = flat_wigner(lmax, G[idx])
    logits = get_grid_evaluator(lmax, level, torch.float64).logits(c)
    assert torch.equal(logits.argmax(dim=1), idx)
    torch.testing.assert_close(
        logits.max(dim=1).values, torch.full((4,), 455.0, dtype=torch.float64), atol=1e-9, rtol=0
    )


# ---------------------------------------------------------------------------------- streamed reductions
CASES = [(6, 1), (4, 2), (2, 3), (0, 1)]


@pytest.mark.parametrize(("lmax", "level"), CASES)
@pytest.mark.parametrize("chunk", [7, None])
def test_streamed_reductions(lmax, level, chunk):
    ev = get_grid_evaluator(lmax, level, torch.float64)
    c = random_coeffs(lmax)
    full = ev.logits(c)
    torch.testing.assert_close(full, dense(lmax, level), atol=1e-9, rtol=0)

    lse = ev.logsumexp(c, chunk_pixels=chunk)
    torch.testing.assert_close(lse, torch.logsumexp(full, dim=1), atol=1e-10, rtol=0)

    lse2, vmax, imax = ev.logsumexp_and_max(c, chunk_pixels=chunk)
    torch.testing.assert_close(lse2, torch.logsumexp(full, dim=1), atol=1e-10, rtol=0)
    ref_max = full.max(dim=1)
    torch.testing.assert_close(vmax, ref_max.values, atol=1e-10, rtol=0)
    if lmax > 0:  # lmax 0 is constant: every index is an argmax
        assert torch.equal(imax, ref_max.indices)
    torch.testing.assert_close(full.gather(1, imax[:, None])[:, 0], vmax, atol=1e-10, rtol=0)
    assert imax.dtype == torch.long

    P, G = ev.n_pix, ev.n_gamma
    plse = ev.pixel_logsumexp(c, chunk_pixels=chunk)
    assert plse.shape == (3, P)
    torch.testing.assert_close(plse, torch.logsumexp(full.reshape(3, P, G), dim=2), atol=1e-10, rtol=0)


@pytest.mark.parametrize(("lmax", "level"), CASES)
def test_logits_at_and_gamma_logits(lmax, level):
    ev = get_grid_evaluator(lmax, level, torch.float64)
    c = random_coeffs(lmax)
    full = ev.logits(c)
    N, P, G = ev.n_points, ev.n_pix, ev.n_gamma
    g = torch.Generator().manual_seed(level)
    shared = torch.randint(0, N, (11,), generator=g)
    shared[0], shared[1] = 0, N - 1
    out = ev.logits_at(c, shared)
    assert out.shape == (3, 11)
    torch.testing.assert_close(out, full[:, shared], atol=1e-10, rtol=0)
    per = torch.randint(0, N, (3, 5), generator=g)
    torch.testing.assert_close(ev.logits_at(c, per), full.gather(1, per), atol=1e-10, rtol=0)

    pix = torch.randint(0, P, (3, 4), generator=g)
    gl = ev.gamma_logits(c, pix)
    assert gl.shape == (3, 4, G)
    expected = full.reshape(3, P, G)[torch.arange(3)[:, None], pix]
    torch.testing.assert_close(gl, expected, atol=1e-10, rtol=0)


def test_float32_streamed_reductions():
    ev = get_grid_evaluator(6, 2, torch.float32)
    c = random_coeffs(6, dtype=torch.float32)
    ref = dense(6, 2)
    lse, vmax, imax = ev.logsumexp_and_max(c, chunk_pixels=13)
    torch.testing.assert_close(lse.double(), torch.logsumexp(ref, 1), atol=1e-4 * ref.abs().max().item(), rtol=0)
    torch.testing.assert_close(vmax.double(), ref.max(1).values, atol=1e-4 * ref.abs().max().item(), rtol=0)
    # the argmax may differ only between near-ties
    torch.testing.assert_close(ref.gather(1, imax[:, None])[:, 0], ref.max(1).values, atol=1e-3, rtol=0)
    assert lse.dtype == vmax.dtype == torch.float32


# ---------------------------------------------------------------------------------- gradients
def test_gradients_match_dense():
    lmax, level = 4, 1
    ev = get_grid_evaluator(lmax, level, torch.float64)
    w = torch.randn(3, ev.n_points, dtype=torch.float64, generator=torch.Generator().manual_seed(1))
    c1 = random_coeffs(lmax).requires_grad_(True)
    c2 = random_coeffs(lmax).requires_grad_(True)
    (ev.logits(c1) * w).sum().backward()
    (dense_grid_logits(c2, lmax, level) * w).sum().backward()
    torch.testing.assert_close(c1.grad, c2.grad, atol=1e-10, rtol=0)

    # streamed reductions and logits_at: gradient equals that of the dense formula
    idx = torch.tensor([[3, 100], [5, 7], [0, 575]])
    P, G = ev.n_pix, ev.n_gamma

    def ref(c):
        return reference_dense_grid_logits(c, lmax, level)

    pairs = [
        (lambda c: ev.logsumexp(c, chunk_pixels=5).sum(), lambda c: torch.logsumexp(ref(c), 1).sum()),
        (lambda c: ev.logsumexp_and_max(c, chunk_pixels=5)[0].sum(), lambda c: torch.logsumexp(ref(c), 1).sum()),
        (lambda c: ev.logits_at(c, idx).pow(2).sum(), lambda c: ref(c).gather(1, idx).pow(2).sum()),
        (
            lambda c: ev.pixel_logsumexp(c, chunk_pixels=5).sum(),
            lambda c: torch.logsumexp(ref(c).reshape(3, P, G), 2).sum(),
        ),
        (
            lambda c: ev.gamma_logits(c, idx // G).pow(2).sum(),
            lambda c: ref(c).reshape(3, P, G)[torch.arange(3)[:, None], idx // G].pow(2).sum(),
        ),
    ]
    for fast, slow in pairs:
        a = random_coeffs(lmax, seed=2).requires_grad_(True)
        b = random_coeffs(lmax, seed=2).requires_grad_(True)
        fast(a).backward()
        slow(b).backward()
        torch.testing.assert_close(a.grad, b.grad, atol=1e-10, rtol=0)


def test_gradcheck_small():
    ev = HealpixGridEvaluator(2, 0, dtype=torch.float64)
    c = random_coeffs(2, batch=1).requires_grad_(True)
    assert torch.autograd.gradcheck(lambda x: ev.logsumexp(x, chunk_pixels=5), (c,))
    assert torch.autograd.gradcheck(lambda x: ev.gamma_logits(x, torch.tensor([[0, 11]])), (c,))


# ---------------------------------------------------------------------------------- cache and memory
def test_get_grid_evaluator_cache():
    a = get_grid_evaluator(2, 1)
    assert get_grid_evaluator(2, 1) is a
    assert get_grid_evaluator(2, 1, torch.float32, "cpu") is a
    assert get_grid_evaluator(2, 1, device=torch.device("cpu")) is a
    assert a.dtype == torch.float32 and a.device == torch.device("cpu")
    b = get_grid_evaluator(2, 1, torch.float64)
    assert b is not a and b.dtype == torch.float64
    assert get_grid_evaluator(2, 2) is not a
    assert get_grid_evaluator(1, 1) is not a


def test_operator_size():
    ev = get_grid_evaluator(6, 2, torch.float64)
    weights = (2 * n_so3_coeffs(6) - n_s2_coeffs(6)) * ev.n_pix * 8
    assert weights == 861 * 192 * 8
    assert weights <= ev.operator_bytes <= weights + (2 * 6 + 1) * ev.n_gamma * 8
    # the limit is on the operator size: exactly enough passes, 1000 bytes does not
    HealpixGridEvaluator(2, 1, dtype=torch.float64, max_operator_bytes=(2 * 35 - 9) * 48 * 8)
    with pytest.raises(ValueError):
        HealpixGridEvaluator(2, 1, dtype=torch.float64, max_operator_bytes=(2 * 35 - 9) * 48 * 8 - 1)
    with pytest.raises(ValueError):
        HealpixGridEvaluator(6, 3, max_operator_bytes=1000)


# ---------------------------------------------------------------------------------- bad input
def test_bad_input():
    ev = get_grid_evaluator(2, 1, torch.float64)
    c = random_coeffs(2)
    for bad in (c[:, :-1], c[0], c[None], torch.zeros(3, 36, dtype=torch.float64)):
        with pytest.raises(ValueError):
            ev.logits(bad)
        with pytest.raises(ValueError):
            ev.logsumexp(bad)
    for method in (ev.logits, ev.logsumexp, ev.logsumexp_and_max, ev.pixel_logsumexp):
        with pytest.raises(ValueError):
            method(c.float())
    with pytest.raises(ValueError):
        ev.logits_at(c.float(), torch.tensor([0]))
    with pytest.raises(ValueError):
        ev.gamma_logits(c.float(), torch.tensor([[0]]))
    with pytest.raises(ValueError):
        ev.logits(c, max_output_bytes=1000)
    assert ev.logits(c, max_output_bytes=3 * ev.n_points * 8).shape == (3, ev.n_points)
    with pytest.raises(ValueError):
        ev.logits(c, max_output_bytes=3 * ev.n_points * 8 - 1)
    N = ev.n_points
    for bad_index in (
        torch.tensor([N]),
        torch.tensor([-1]),
        torch.tensor([[0], [1]]),  # batch 2 != 3
        torch.tensor([0.0, 1.0]),
        torch.zeros(3, 1, 1, dtype=torch.long),
    ):
        with pytest.raises(ValueError):
            ev.logits_at(c, bad_index)
    for args in ((-1, 1), (2, -1), (2, 11), (2, 2.5), (2.5, 1), (True, 1)):
        with pytest.raises(ValueError):
            HealpixGridEvaluator(*args)
        with pytest.raises(ValueError):
            get_grid_evaluator(*args)


def test_evaluator_at_arbitrary_rotations_consistency():
    """logits_at on grid indices equals flat_wigner(grid rotation) @ coeffs (e3nn path)."""
    lmax, level = 6, 2
    ev = get_grid_evaluator(lmax, level, torch.float64)
    c = random_coeffs(lmax)
    idx = torch.tensor([1, 400, 1535])
    G = so3_healpix_grid(level, dtype=torch.float64)[idx]
    torch.testing.assert_close(ev.logits_at(c, idx), c @ reference_flat_wigner(lmax, G).T, atol=1e-10, rtol=0)


def test_gamma_logits_rejects_out_of_range_pixels():
    ev = get_grid_evaluator(2, 1, torch.float64)
    c = random_coeffs(2, batch=2)
    with pytest.raises(ValueError, match="pixel indices"):
        ev.gamma_logits(c, torch.tensor([[-1], [0]]))
    with pytest.raises(ValueError, match="pixel indices"):
        ev.gamma_logits(c, torch.tensor([[ev.n_pix], [0]]))


def test_gamma_logits_accepts_shared_pixels():
    ev = get_grid_evaluator(2, 1, torch.float64)
    c = random_coeffs(2, batch=2)
    pix = torch.tensor([3, 17, 47])
    torch.testing.assert_close(ev.gamma_logits(c, pix), ev.gamma_logits(c, pix[None].expand(2, -1)))
    full = ev.logits(c).view(2, ev.n_pix, ev.n_gamma)
    torch.testing.assert_close(ev.gamma_logits(c, pix), full[:, pix])


def test_an_evaluator_first_built_under_inference_mode_still_trains():
    """The evaluator is cached per process; when its first use is a validation loop (torch.inference_mode,
    e.g. ``train_grid_level=4`` with ``val_grid_level`` following it), the training loss must still
    backpropagate through it (it crashed with "Inference tensors cannot be saved for backward")."""
    from image2sphere.so3.grid_eval import _cached

    _cached.cache_clear()
    with torch.inference_mode():
        evaluator = get_grid_evaluator(3, 4)
    coeffs = torch.randn(2, n_so3_coeffs(3), requires_grad=True)
    evaluator.logsumexp(coeffs).sum().backward()
    assert coeffs.grad is not None and bool(coeffs.grad.abs().sum() > 0)
    _cached.cache_clear()
