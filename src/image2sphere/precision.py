"""Mixed precision (``trainer.precision=bf16-mixed`` or ``16-mixed``), safe by construction
(docs/configuration.md#mixed-precision).

Under Lightning's mixed precision every training, validation and test step runs inside
``torch.autocast``. In this package only the image encoder follows it (its convolutions run in
bfloat16 or float16); everything after the encoder computes in float32 (or float64, where it already
does) whatever autocast region encloses the call.

Conventions
-----------
* **Reduced precision:** the encoder's forward pass only (:meth:`image2sphere.nn.base.Float32Head.encode`).
  Its feature map is cast to float32 before anything else sees it.
* **Always float32:** the network's head (projectors, S2 and SO(3) convolutions, MLPs, Wigner and
  grid tables), ``output_distribution``, ``loss``, every
  :class:`~image2sphere.distributions.base.PoseDistribution` method (log densities, grid
  logsumexp, every normaliser, modes, samples) and the tables cached for later calls.
* **Outside autocast nothing changes:** :func:`float32_region` then calls the function as it is,
  so float32 and float64 numerics are bit for bit those without this module.

The mechanism is in two base classes, not in the methods:

* :class:`~image2sphere.nn.base.Float32Head` (every pose network) wraps ``forward``,
  ``output_distribution`` and ``loss`` of each subclass in :func:`float32_region` when the subclass
  is defined (``__init_subclass__``); ``encode`` runs the encoder under the autocast that enclosed
  the call (:func:`encoder_autocast`).
* :class:`~image2sphere.distributions.base.PoseDistribution` wraps every method of every family
  (:func:`float32_methods`).
"""

from __future__ import annotations

import contextlib
import functools
import inspect
from collections.abc import Callable, Iterator
from contextvars import ContextVar
from typing import NamedTuple, TypeVar

import torch

__all__ = [
    "REDUCED_DTYPES",
    "AutocastState",
    "autocast_enabled",
    "constant_cache",
    "current_autocast",
    "encoder_autocast",
    "float32_methods",
    "float32_region",
    "to_float32",
]

#: the dtypes autocast computes in; tensors of these are cast to float32 on entering a float32 region
REDUCED_DTYPES = (torch.float16, torch.bfloat16)

# the device types whose autocast state is read and restored (those this build of torch knows)
_DEVICE_TYPES = tuple(
    d for d in ("cpu", "cuda", "xpu", "mps", "hpu") if torch.amp.autocast_mode.is_autocast_available(d)
)

F = TypeVar("F", bound=Callable)


def autocast_enabled() -> bool:
    """True inside an autocast region of any device type."""
    any_enabled = getattr(torch._C, "_is_any_autocast_enabled", None)
    if any_enabled is not None:  # one call instead of one per device type
        return any_enabled()
    return any(torch.is_autocast_enabled(d) for d in _DEVICE_TYPES)


class AutocastState(NamedTuple):
    """The autocast in force at a point: ``(device type, dtype)`` of each device type where it is on,
    and whether autocast caches its casts of the weights."""

    dtypes: tuple[tuple[str, torch.dtype], ...]
    cache_enabled: bool


def current_autocast() -> AutocastState | None:
    """The autocast in force here; ``None`` outside autocast."""
    if not autocast_enabled():
        return None
    on = tuple((d, torch.get_autocast_dtype(d)) for d in _DEVICE_TYPES if torch.is_autocast_enabled(d))
    return AutocastState(on, torch.is_autocast_cache_enabled())


# the autocast that enclosed the float32 region we are in (None: not in one)
_ENCLOSING: ContextVar[AutocastState | None] = ContextVar("image2sphere_enclosing_autocast", default=None)


def to_float32(x):
    """A float16 or bfloat16 tensor as float32 (differentiable); anything else unchanged."""
    if isinstance(x, torch.Tensor) and x.dtype in REDUCED_DTYPES:
        return x.float()
    return x


@contextlib.contextmanager
def _autocast_off(state: AutocastState) -> Iterator[None]:
    """Autocast off for every device type of ``state``, which is remembered as the enclosing autocast."""
    token = _ENCLOSING.set(state)
    try:
        with contextlib.ExitStack() as stack:
            for device_type, _ in state.dtypes:
                stack.enter_context(torch.autocast(device_type, enabled=False))
            yield
    finally:
        _ENCLOSING.reset(token)


def float32_region(fn: F) -> F:
    """``fn`` made to compute in float32 under any enclosing autocast.

    Outside autocast ``fn`` is called as it is. Inside, autocast is turned off for the call (for every
    device type where it is on), float16/bfloat16 tensor arguments are cast to float32, and the
    enclosing autocast is remembered so that :func:`encoder_autocast` can bring it back for the
    encoder. A generator function runs each of its steps so (not the caller's code between them).
    Applying it twice is applying it once.
    """
    if getattr(fn, "__float32_region__", False):
        return fn

    if inspect.isgeneratorfunction(fn):

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            state = current_autocast()
            if state is None:
                return (yield from fn(*args, **kwargs))
            steps = fn(*(to_float32(a) for a in args), **{k: to_float32(v) for k, v in kwargs.items()})
            while True:
                with _autocast_off(state):
                    try:
                        item = next(steps)
                    except StopIteration as stop:
                        return stop.value
                yield item

    else:

        @functools.wraps(fn)
        def wrapper(*args, **kwargs):
            state = current_autocast()
            if state is None:  # no autocast (or already in a float32 region): nothing changes
                return fn(*args, **kwargs)
            args = tuple(to_float32(a) for a in args)
            kwargs = {k: to_float32(v) for k, v in kwargs.items()}
            with _autocast_off(state):
                return fn(*args, **kwargs)

    wrapper.__float32_region__ = True
    return wrapper  # type: ignore[return-value]


@contextlib.contextmanager
def encoder_autocast() -> Iterator[bool]:
    """Inside a float32 region, the autocast that enclosed it again (for the encoder); elsewhere the
    autocast in force, unchanged. Yields whether autocast is on inside."""
    state = _ENCLOSING.get()
    if state is None or autocast_enabled():
        yield autocast_enabled()
        return
    token = _ENCLOSING.set(None)  # a float32 region inside the encoder starts afresh
    try:
        with contextlib.ExitStack() as stack:
            for device_type, dtype in state.dtypes:
                stack.enter_context(torch.autocast(device_type, dtype=dtype, cache_enabled=state.cache_enabled))
            yield True
    finally:
        _ENCLOSING.reset(token)


def float32_methods(cls: type, names: tuple[str, ...] | None = None) -> type:
    """Wrap methods defined in ``cls`` itself (not inherited) in :func:`float32_region`: those of
    ``names``, or with ``None`` every function, classmethod, staticmethod and property getter (``__init__``
    included, other dunder methods not). Returns ``cls``."""
    for name, attr in list(vars(cls).items()):
        if names is not None:
            if name not in names:
                continue
        elif name.startswith("__") and name != "__init__":
            continue
        if isinstance(attr, (classmethod, staticmethod)):
            wrapped = type(attr)(float32_region(attr.__func__))
        elif isinstance(attr, property) and attr.fget is not None:
            wrapped = attr.getter(float32_region(attr.fget))
        elif inspect.isfunction(attr):
            wrapped = float32_region(attr)
        else:
            continue
        setattr(cls, name, wrapped)
    return cls


def constant_cache(maxsize: int | None = 8) -> Callable[[F], F]:
    """``functools.lru_cache`` for functions that build constant tensors (grids, index tables, quadrature
    rules) once per process, whatever context the first call comes from: in float32 under any autocast
    (:func:`float32_region`), and never as inference tensors. A first call from a test or validation loop
    (``torch.inference_mode``) would otherwise cache an inference tensor, and every later training step
    that saves it for backward would fail ("Inference tensors cannot be saved for backward")."""

    def decorate(fn: F) -> F:
        @functools.wraps(fn)
        def build(*args, **kwargs):
            with torch.inference_mode(False):
                return fn(*args, **kwargs)

        return functools.lru_cache(maxsize=maxsize)(float32_region(build))

    return decorate
