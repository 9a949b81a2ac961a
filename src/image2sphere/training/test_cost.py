"""How long a test will take, said before it is paid.

The test scores every image on the whole SO(3) grid of ``eval_grid_level`` (and the spread on the grid of
``model.spread_grid_level``): its cost grows eightfold per level, and differs by orders of magnitude
between methods (a Fourier signal is evaluated by one matrix product per grid chunk; a flow or IPDF runs a
network on every grid point). :func:`estimate_test_seconds` measures the method as it is, on this device:
it scores one blank image on small grids (:func:`probe_cost`, from level 1 up while the grid's share of the
time is too small to measure), fits ``seconds = fixed + per_point * points`` and extrapolates to the test's
grids and number of images. That takes well under a second and is accurate
to a factor of about two (a batch shares the fixed part, a big grid has cache misses a small one has not):
enough to tell minutes from hours. :func:`announce_test_cost` (called when the test starts) logs the
estimate, as a warning with the way to make it cheaper when it exceeds :data:`LONG_TEST_SECONDS`.
"""

from __future__ import annotations

import contextlib
import logging
import math
import time

import torch

from image2sphere.so3.grid import so3_grid_size

__all__ = ["LONG_TEST_SECONDS", "announce_test_cost", "estimate_test_seconds", "format_duration", "probe_cost"]

log = logging.getLogger(__name__)

#: an estimated test time (seconds) above which the start of the test says how to lower it
LONG_TEST_SECONDS = 300.0
#: the grid levels the probe starts on. It goes up one level at a time while the grid's share of the time is too
#: small to measure (the larger level took less than twice the smaller one's time: a Fourier method's encoder
#: outweighs its small grids, and a millisecond of noise then read as a per-point cost 20 times too high),
#: never above the test's own level or :data:`PROBE_MAX_LEVEL`, and fits the last two levels
PROBE_LEVELS = (1, 2)
PROBE_MAX_LEVEL = 4


def _points(level: int | None) -> int:
    return 0 if level is None else math.prod(so3_grid_size(level))


def _blank_batch(module, image_size: int | tuple[int, int], device: torch.device) -> dict[str, torch.Tensor]:
    """One grey image with the identity as its only ground truth, in the layout of a test batch and in the
    dtype of the module's weights (``trainer.precision=64`` makes them float64)."""
    height, width = (image_size, image_size) if isinstance(image_size, int) else tuple(image_size)
    dtype = next((p.dtype for p in module.parameters() if p.is_floating_point()), torch.float32)
    return {
        "image": torch.zeros(1, 3, height, width, device=device, dtype=dtype),
        "class_index": torch.zeros(1, dtype=torch.long, device=device),
        "index": torch.zeros(1, dtype=torch.long, device=device),
        "rotations": torch.eye(3, device=device, dtype=dtype)[None, None],
        "mask": torch.ones(1, 1, dtype=torch.bool, device=device),
    }


def _timed(module, batch: dict, level: int) -> float:
    if batch["image"].device.type == "cuda":
        torch.cuda.synchronize()
    start = time.perf_counter()
    module._evaluate(batch, level, level, calibration=True)
    if batch["image"].device.type == "cuda":
        torch.cuda.synchronize()
    return time.perf_counter() - start


def probe_cost(module, max_level: int = PROBE_MAX_LEVEL) -> tuple[float, float] | None:
    """``(fixed, per_point)`` seconds of one image's test with ``module`` on its device: a blank image
    scored on the grids of :data:`PROBE_LEVELS` and above (see there), up to ``max_level``; ``None`` where the
    module's network does not say its image size. Leaves the module, its records and the random state as they
    were (the probe draws nothing)."""
    image_size = getattr(getattr(module, "net", None), "image_size", None)
    if image_size is None:
        return None
    batch = _blank_batch(module, image_size, module.device)

    def seconds(level: int) -> float:
        _timed(module, batch, level)  # the first call at a level builds its caches: not timed
        # the faster of two tries: a busy machine slows single calls by several times
        return min(_timed(module, batch, level), _timed(module, batch, level))

    levels = list(PROBE_LEVELS)
    with torch.inference_mode():
        times = [seconds(level) for level in levels]
        while times[-1] < 2 * times[-2] and levels[-1] < max_level:
            levels.append(levels[-1] + 1)
            times.append(seconds(levels[-1]))
    (n0, n1), (t0, t1) = [2 * _points(lv) for lv in levels[-2:]], times[-2:]  # each probe sweeps twice
    per_point = max(t1 - t0, 0.0) / (n1 - n0)
    return max(t1 - per_point * n1, 0.0), per_point


def estimate_test_seconds(cost: tuple[float, float], n_images: int, level: int, spread_level: int | None) -> float:
    """Seconds the test of ``n_images`` images at grid ``level`` (spread at ``spread_level``) takes at the
    :func:`probe_cost` ``cost``."""
    fixed, per_point = cost
    return n_images * (fixed + per_point * (_points(level) + _points(spread_level)))


def format_duration(seconds: float) -> str:
    if seconds < 90:
        return f"{seconds:.0f} s"
    if seconds < 5400:
        return f"{seconds / 60:.0f} min"
    return f"{seconds / 3600:.1f} h"


def _probe_as_tested(module, plugin, level: int) -> tuple[float, float] | None:
    """:func:`probe_cost` in the test's context (``trainer.precision=64``: float64 by default), as the test will
    run, up to the test's own level; ``None`` on any error (an estimate must never stop a test)."""
    try:
        with plugin.test_step_context() if plugin is not None else contextlib.nullcontext():
            return probe_cost(module, max(min(PROBE_MAX_LEVEL, level), PROBE_LEVELS[-1]))
    except Exception as e:  # noqa: BLE001
        log.debug("no estimate of the test's time: %r", e)
        return None


def announce_test_cost(module, n_images: int, level: int, spread_level: int | None, key: str) -> float | None:
    """Log the estimated time of the test (see the module docstring); ``key`` is the setting that lowers
    the grid level (``eval_grid_level``). Returns the estimate (``None``: no estimate)."""
    if n_images <= 0:
        return None
    trainer = getattr(module, "_trainer", None)
    plugin = getattr(trainer, "precision_plugin", None) if trainer is not None else None
    if str(getattr(trainer, "precision", "32-true")) not in ("32-true", "32", "64-true", "64"):
        return None  # mixed precision: the probe would not run as the test does (not estimated yet)
    cost = _probe_as_tested(module, plugin, level)
    if cost is None:
        return None
    seconds = estimate_test_seconds(cost, n_images, level, spread_level)
    if seconds > LONG_TEST_SECONDS:  # measured again before a warning: a moment's slowdown is no reason for one
        again = _probe_as_tested(module, plugin, level)
        seconds_again = math.inf if again is None else estimate_test_seconds(again, n_images, level, spread_level)
        if seconds_again < seconds:
            cost, seconds = again, seconds_again
    line = (
        f"The test of {n_images} images on the grid of level {level} will take about {format_duration(seconds)} "
        f"on this {module.device.type} (estimated by scoring one image on small grids)"
    )
    if seconds > LONG_TEST_SECONDS and level > 1:
        lower = estimate_test_seconds(cost, n_images, level - 1, spread_level)
        log.warning("%s; %s=%d would take about %s", line, key, level - 1, format_duration(lower))
    else:
        log.info(line)
    return seconds
