"""Checks of scalar arguments and config values, shared by every layer (imports nothing of the project).

Each raises ``ValueError`` naming the argument or config key (``name``), the rule, and the value
given, e.g. ``dataset.batch_size must be an integer >= 1, got 0``. ``bool`` is refused where a number
is expected (``True`` is an ``int`` to Python, never a count to a user).
"""

from __future__ import annotations

import math

__all__ = ["check_int", "check_number"]


def check_int(name: str, value, minimum: int = 0, *, allow_none: bool = False, note: str = "") -> int | None:
    """``value`` if it is an ``int`` (not a ``bool``) ``>= minimum`` (or ``None`` with ``allow_none``).

    ``note`` is added to the rule in the message (e.g. ``" (0: no refinement)"``).
    """
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        alternative = " or None" if allow_none else ""
        raise ValueError(f"{name} must be an integer >= {minimum}{alternative}{note}, got {value!r}")
    return value


def check_number(name: str, value, minimum: float = 0.0) -> float:
    """``float(value)`` if it is a finite real number (not a ``bool``) ``>= minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < minimum:
        raise ValueError(f"{name} must be a finite number >= {minimum:g}, got {value!r}")
    return float(value)
