"""How far a long computation inside one evaluation batch has got: a hook between the mathematics and the
terminal.

The grid sweeps (:mod:`image2sphere.distributions`, :mod:`image2sphere.so3.grid_eval`) call :func:`report`
after each chunk of a grid; the training run's progress bar
(:class:`~image2sphere.training.progress.EpochProgressBar`) installs itself with :func:`set_reporter`
while it draws a validation, test or predict batch, and shows ``grid L 12/40 chunks`` next to the batch's
count. Without a reporter (a library call, another rank, training, a switched-off bar) :func:`report`
is one global read. This module imports nothing of the package, so that the mathematics does not depend
on the training code.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["report", "reporter", "set_reporter"]

Reporter = Callable[[int, int, str, str], None]
_reporter: Reporter | None = None


def report(done: int, total: int, what: str, unit: str = "") -> None:
    """``done`` of ``total`` steps of ``what`` (e.g. ``report(12, 40, "grid 5", "chunks")``) to the reporter
    installed now, if any. A plain module attribute rather than a ContextVar: a sweep may score its chunks on
    a thread of its own, which would not see a ContextVar set on the main thread."""
    reporter = _reporter
    if reporter is not None:
        reporter(done, total, what, unit)


def reporter() -> Reporter | None:
    """The reporter installed now (``None``: none)."""
    return _reporter


def set_reporter(reporter: Reporter | None) -> Reporter | None:
    """Install ``reporter`` (``None``: none); returns the one it replaces."""
    global _reporter
    previous, _reporter = _reporter, reporter
    return previous
