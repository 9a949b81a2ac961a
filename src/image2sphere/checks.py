"""Refusals, and checks of scalar arguments and config values, shared by every layer (imports nothing of the
project).

**Refusals.** Where the project's code refuses a value, a path or a file that a user gave, it raises a
:class:`Refusal`: a :class:`ConfigError` (a ``ValueError``: a config value, an argument, a file's content),
an :class:`InputNotFoundError` (a ``FileNotFoundError``: a dataset, a checkpoint, an image that is not
there) or an :class:`OutputExistsError` (a ``FileExistsError``: a file or folder that would be
overwritten). Their message names the key or file and what to do. The entry points (``src.train``,
``src.eval``, ``src.predict``) print exactly these in one line; every other exception is a bug to report
and keeps its traceback. Code that calls the library catches them as the built-in types they extend.

**Checks.** Each raises :class:`ConfigError` naming the argument or config key (``name``), the rule, and
the value given, e.g. ``dataset.batch_size must be an integer >= 1, got 0``. ``bool`` is refused where a
number is expected (``True`` is an ``int`` to Python, never a count to a user).
"""

from __future__ import annotations

import math

__all__ = ["ConfigError", "InputNotFoundError", "OutputExistsError", "Refusal", "check_int", "check_number"]


class Refusal(Exception):  # noqa: N818 - what it is, not an "Error" of the program
    """The project refused something the user gave (module docstring); only ever raised as one of the three
    kinds below."""


class ConfigError(Refusal, ValueError):
    """A config value, argument or file content the project refuses; the message names it and the rule."""


class InputNotFoundError(Refusal, FileNotFoundError):
    """A dataset, checkpoint, image or other input that is not where the user said; the message says where
    it was looked for and how to get it."""


class OutputExistsError(Refusal, FileExistsError):
    """A file or folder that a run would overwrite; nothing was written, and the message says what to do."""


def check_int(name: str, value, minimum: int = 0, *, allow_none: bool = False, note: str = "") -> int | None:
    """``value`` if it is an ``int`` (not a ``bool``) ``>= minimum`` (or ``None`` with ``allow_none``).

    ``note`` is added to the rule in the message (e.g. ``" (0: no refinement)"``).
    """
    if value is None and allow_none:
        return None
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        alternative = " or None" if allow_none else ""
        raise ConfigError(f"{name} must be an integer >= {minimum}{alternative}{note}, got {value!r}")
    return value


def check_number(name: str, value, minimum: float = 0.0) -> float:
    """``float(value)`` if it is a finite real number (not a ``bool``) ``>= minimum``."""
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value) or value < minimum:
        raise ConfigError(f"{name} must be a finite number >= {minimum:g}, got {value!r}")
    return float(value)
