"""The cost of a test said before it is paid (training/test_cost.py), and progress inside a long evaluation
batch (image2sphere.batch_progress, reported by every grid sweep). Quick tier: about 2 s besides the session's
``tiny_run``."""

from __future__ import annotations

import logging
import math

import pytest
import torch

from image2sphere import batch_progress
from image2sphere.so3.grid import so3_grid_size
from image2sphere.training import test_cost
from image2sphere.training.test_cost import (
    LONG_TEST_SECONDS,
    announce_test_cost,
    estimate_test_seconds,
    format_duration,
    probe_cost,
)


def points(level: int) -> int:
    return math.prod(so3_grid_size(level))


class _Net(torch.nn.Module):
    image_size = 8


class _Module(torch.nn.Module):
    """What the probe uses of a PoseEstimationModule: ``net.image_size``, ``device``, ``_evaluate``."""

    def __init__(self):
        super().__init__()
        self.net = _Net()
        self.calls: list[tuple[int, int | None, bool, tuple]] = []

    @property
    def device(self) -> torch.device:
        return torch.device("cpu")

    def _evaluate(self, batch, level, spread_level, calibration=False):
        self.calls.append((level, spread_level, calibration, tuple(batch["image"].shape)))
        return {}


@pytest.fixture
def linear_clock(monkeypatch):
    """``_timed`` as a machine whose test of one image costs 0.02 s plus 3 us per grid point swept (the test's
    and the spread's grids), on every call: the probe must recover both numbers."""
    fixed, per_point = 0.02, 3e-6

    def timed(module, batch, level):
        module._evaluate(batch, level, level, calibration=True)
        return fixed + per_point * 2 * points(level)

    monkeypatch.setattr(test_cost, "_timed", timed)
    return fixed, per_point


def test_the_probe_recovers_fixed_and_per_point_costs_and_extrapolates(linear_clock):
    module = _Module()
    fixed, per_point = probe_cost(module)
    assert fixed == pytest.approx(linear_clock[0]) and per_point == pytest.approx(linear_clock[1])
    # one blank image, scored as a test batch is (calibration pairs, spread), on the small grids only
    assert {c[0] for c in module.calls} == set(test_cost.PROBE_LEVELS)
    assert all(c[2] and c[3] == (1, 3, 8, 8) for c in module.calls)
    expected = 200 * (0.02 + 3e-6 * (points(5) + points(4)))
    assert estimate_test_seconds((fixed, per_point), 200, 5, 4) == pytest.approx(expected)
    assert estimate_test_seconds((fixed, per_point), 200, 5, None) == pytest.approx(200 * (0.02 + 3e-6 * points(5)))


def test_a_small_grid_share_is_probed_on_larger_grids_and_a_moments_slowdown_warns_of_nothing(monkeypatch, caplog):
    """A Fourier method at the default run's size: 10 ms of encoder per image and 30 ns per grid point, so levels
    1 and 2 differ by 0.2 ms. On the default run (400 images, level 5, spread 4) a 2 ms slowdown of level 2's
    calls read as a per-point cost ten times too high and warned "about 5 min" for a test of 31 s. The probe
    goes up to the levels where the grid's share shows, and a long estimate is measured again before a
    warning."""
    fixed, per_point = 0.010, 3e-8
    slow = {"calls": 6}  # the first probe's three calls at level 2 (one untimed) come 2 ms late

    def timed(module, batch, level):
        module._evaluate(batch, level, level, calibration=True)
        late = 0.002 if level == 2 and slow["calls"] > 0 else 0.0
        slow["calls"] -= level == 2
        return fixed + per_point * 2 * points(level) + late

    monkeypatch.setattr(test_cost, "_timed", timed)
    module = _Module()
    probed = probe_cost(module)
    assert sorted({c[0] for c in module.calls}) == [1, 2, 3, 4]  # up to where the grid's time shows
    assert probed == (pytest.approx(fixed, rel=1e-6), pytest.approx(per_point, rel=1e-6))
    true = estimate_test_seconds((fixed, per_point), 400, 5, 4)  # about 84 s
    caplog.set_level(logging.INFO, logger=test_cost.__name__)
    slow["calls"], module.calls = 6, []
    assert announce_test_cost(module, 400, 5, 4, "eval_grid_level") == pytest.approx(true, rel=1e-6)
    (record,) = caplog.records
    assert record.levelno == logging.INFO
    # never above the test's own level: a level-3 test is probed on levels 1 to 3 and not extrapolated
    slow["calls"], module.calls = 0, []
    assert announce_test_cost(module, 6, 3, 2, "eval_grid_level") == pytest.approx(
        estimate_test_seconds((fixed, per_point), 6, 3, 2), rel=1e-6
    )
    assert max(c[0] for c in module.calls) == 3

    def stays_slow(module, batch, level):  # a test that is long: the second look confirms it
        module._evaluate(batch, level, level, calibration=True)
        return 0.02 + 3e-6 * 2 * points(level)

    monkeypatch.setattr(test_cost, "_timed", stays_slow)
    caplog.clear()
    assert announce_test_cost(_Module(), 200, 5, 4, "eval_grid_level") > LONG_TEST_SECONDS
    assert [r.levelno for r in caplog.records] == [logging.WARNING]


def test_a_long_test_is_announced_with_the_level_that_makes_it_cheaper(linear_clock, caplog):
    module = _Module()
    caplog.set_level(logging.INFO, logger=test_cost.__name__)
    seconds = announce_test_cost(module, 200, 5, 4, "eval_grid_level")
    assert seconds > LONG_TEST_SECONDS  # 200 * (0.02 + 3e-6 * 2.65M) = about 27 min
    (record,) = caplog.records
    assert record.levelno == logging.WARNING
    lower = estimate_test_seconds(linear_clock, 200, 4, 4)
    assert record.getMessage() == (
        f"The test of 200 images on the grid of level 5 will take about {format_duration(seconds)} on this cpu "
        f"(estimated by scoring one image on small grids); eval_grid_level=4 would take about {format_duration(lower)}"
    )
    caplog.clear()
    assert announce_test_cost(module, 6, 3, 2, "eval_grid_level") < LONG_TEST_SECONDS
    (record,) = caplog.records
    assert record.levelno == logging.INFO and "eval_grid_level" not in record.getMessage()


def test_no_estimate_without_an_image_size_or_images(caplog):
    module = _Module()
    assert announce_test_cost(module, 0, 5, 4, "eval_grid_level") is None
    del _Net.image_size
    try:
        assert announce_test_cost(module, 10, 5, 4, "eval_grid_level") is None
    finally:
        _Net.image_size = 8
    assert not module.calls and not caplog.records


@pytest.mark.parametrize(("seconds", "text"), [(12.4, "12 s"), (600, "10 min"), (4 * 3600, "4.0 h")])
def test_durations_read_as_a_person_would_say_them(seconds, text):
    assert format_duration(seconds) == text


def test_a_real_module_is_probed_without_changing_what_it_then_computes(tiny_run):
    """The tiny run's module: the probe leaves its records, tie-break counter and outputs as they were."""
    from image2sphere.training.checkpoint import build_module, load_checkpoint

    ckpt = tiny_run / "checkpoints" / "last.ckpt"
    module = build_module(load_checkpoint(ckpt), ckpt).eval()
    images = torch.rand(2, 3, 32, 32, generator=torch.Generator().manual_seed(0))
    with torch.inference_mode():
        before = module(images)
        state = torch.get_rng_state()
        cost = probe_cost(module)
        assert torch.equal(torch.get_rng_state(), state)
        assert torch.equal(module(images), before)
    assert cost[0] >= 0 and cost[1] >= 0 and not getattr(module, "_records", {})


def test_the_run_says_how_long_its_test_will_take(tiny_run):
    stdout = (tiny_run.parent / "stdout.txt").read_text()
    # TINY: 3 test images of each of the two shapes, one batch of 6, at eval_grid_level=3
    assert "The test of 6 images on the grid of level 3 will take about " in stdout


@pytest.mark.parametrize("family", ["fourier", "grid_protocol"])
def test_every_grid_sweep_reports_its_chunks(family, monkeypatch):
    """The Fourier signal's evaluator and the grid-protocol families (flow, IPDF, ...) both report each chunk
    of the grid they sweep, in order, through image2sphere.batch_progress."""
    seen: list[tuple[int, int, str, str]] = []
    previous = batch_progress.set_reporter(lambda *a: seen.append(a))
    try:
        if family == "fourier":
            from image2sphere.so3.grid_eval import get_grid_evaluator
            from image2sphere.so3.wigner import n_so3_coeffs

            evaluator = get_grid_evaluator(2, 3, torch.float32, torch.device("cpu"))
            evaluator.logsumexp_and_max(torch.randn(2, n_so3_coeffs(2)), chunk_pixels=100)
            total = -(-so3_grid_size(3)[0] // 100)
        else:
            from image2sphere.distributions import grid_protocol

            monkeypatch.setattr(grid_protocol, "CHUNK_POINTS", 20_000)
            dist = _grid_protocol_distribution()
            dist.grid_logsumexp_and_max(3)
            total = len(list(dist._grid_chunks(3)))
    finally:
        batch_progress.set_reporter(previous)
    assert total > 1
    assert [s[:2] for s in seen[:total]] == [(i, total) for i in range(total)]
    assert all(s[2] == "grid 3" and s[3] == "chunks" for s in seen)


def _grid_protocol_distribution():
    """A grid-protocol family with a cheap density: the matrix Fisher distribution of one random parameter."""
    from image2sphere.distributions.matrix_fisher import MatrixFisher

    return MatrixFisher(torch.randn(1, 3, 3, generator=torch.Generator().manual_seed(1)))


def test_without_a_reporter_a_sweep_reports_to_nobody():
    assert batch_progress.set_reporter(None) is None
    batch_progress.report(1, 2, "grid 3", "chunks")  # nothing installed: nothing happens
