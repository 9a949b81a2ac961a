"""The one interface every pose method's output goes through: a batch of distributions over SO(3).

Conventions (docs/conventions.md#densities)
-------------------------------------------
* Rotations ``(..., 3, 3)``, ``x_camera = R @ x_object``.
* Densities are w.r.t. the Haar measure normalised to total volume ``pi^2``: a uniform distribution
  has log density ``-log(pi^2)`` (:data:`LOG_UNIFORM_DENSITY`).
* Every density method is scored by the grid protocol (:mod:`image2sphere.distributions.grid_protocol`):
  its log density on the HEALPix SO(3) grid of a level, put through a softmax, swept in chunks; the
  highest-density-region masses of query rotations come out of the same sweep
  (:mod:`image2sphere.distributions.hdr_masses`). A family with a closed-form normaliser also gives
  its continuous density (:meth:`PoseDistribution.exact_log_density`).

The contract
------------
A family subclasses :class:`PoseDistribution`, sets :attr:`~PoseDistribution.batch_size`,
:attr:`~PoseDistribution.dtype` and :attr:`~PoseDistribution.device` and implements
:meth:`~PoseDistribution.unnormalized_log_density` (and, where the family has them,
:meth:`~PoseDistribution.exact_log_normalizer`, :meth:`~PoseDistribution.exact_mode` and
:meth:`~PoseDistribution.exact_sample`). Everything else (grid reductions, nearest-point log density,
modes, sampling on the grid, points above a threshold, HDR masses) comes from the grid protocol, which
a family overrides only where it computes something differently (the Fourier family:
:mod:`image2sphere.distributions.fourier`). A point regressor subclasses :class:`PointEstimate`
instead: it has a mode and no density.

* **Tempering** (recalibration, docs/evaluation.md#recalibration): :meth:`PoseDistribution.tempered`
  gives the distribution with density proportional to ``p(R) ** (1 / T)`` for a temperature ``T > 0``
  (``T < 1`` sharpens, ``T > 1`` broadens). It keeps the order of the rotations by density, so the
  mode, the ranking and every accuracy are unchanged. The default, :class:`TemperedDistribution`,
  divides the unnormalised log density by ``T`` and normalises on the grid; a family where the power
  stays in the family overrides it (the Fourier family scales its coefficients, the matrix Fisher
  family its parameter matrix, the Euler bins their bin probabilities, all exactly).

* **Mixed precision** (:mod:`image2sphere.precision`): every method of this class, of the grid
  protocol and of each family (``__init__``, class methods and property getters included) computes in
  float32 (or float64 where the family's parameters are) under an enclosing ``torch.autocast``:
  :meth:`PoseDistribution.__init_subclass__` wraps them, when a family is defined, in
  :func:`~image2sphere.precision.float32_region` (autocast off, float16/bfloat16 tensor arguments cast
  to float32). Log densities, grid sweeps, logsumexps, normalisers, modes and samples are never
  evaluated in reduced precision, whoever calls them; the grid tables cached for later calls are built
  the same way. Without autocast nothing changes.
"""

from __future__ import annotations

import math

import torch

from image2sphere.checks import ConfigError, check_int
from image2sphere.distributions.grid_protocol import LOG_UNIFORM_DENSITY, GridProtocol, check_threshold
from image2sphere.precision import float32_methods
from image2sphere.so3.rotations import check_rotation_matrix

__all__ = [
    "LOG_UNIFORM_DENSITY",
    "DensityNotAvailable",
    "PointEstimate",
    "PoseDistribution",
    "TemperedDistribution",
    "check_num_components",
    "check_temperature",
    "check_threshold",
]


class DensityNotAvailable(NotImplementedError):
    """The method predicts a rotation, not a distribution: it has no density (log likelihood, spread)."""


def check_num_components(num_components) -> int:
    """The number of components of a mixture family: an integer >= 1, else ``ValueError``."""
    return check_int("num_components", num_components, 1)


def check_temperature(temperature, name: str = "temperature") -> float:
    """A temperature: a finite number > 0, else ``ValueError`` naming ``name``."""
    number = isinstance(temperature, (int, float)) and not isinstance(temperature, bool)
    if not number or not math.isfinite(temperature) or temperature <= 0:
        raise ConfigError(f"{name} must be a finite number > 0 (1 leaves a distribution as it is), got {temperature!r}")
    return float(temperature)


class PoseDistribution(GridProtocol):
    """A batch of ``B`` distributions over SO(3) (see the module docstring): the contract below, and
    the grid protocol's methods (:class:`~image2sphere.distributions.grid_protocol.GridProtocol`).

    Subclasses set :attr:`batch_size`, :attr:`dtype` and :attr:`device` (e.g. from their parameter
    tensor) and implement :meth:`unnormalized_log_density`.
    """

    #: False for point regressors (:class:`PointEstimate`): no density, log likelihood or spread
    has_density: bool = True
    batch_size: int
    dtype: torch.dtype
    device: torch.device

    def __init_subclass__(cls, **kwargs):
        """Every method a family defines computes in float32 under autocast (module docstring)."""
        super().__init_subclass__(**kwargs)
        float32_methods(cls)

    # ------------------------------------------------------------------ what a family implements
    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """Log density up to a constant per distribution at ``(K, 3, 3)`` (shared) or ``(B, K, 3, 3)``
        rotations: ``(B, K)``. Differentiable w.r.t. the distribution's parameters."""
        raise NotImplementedError

    def exact_log_normalizer(self) -> torch.Tensor:
        """``log`` of the integral of ``exp(unnormalized_log_density)`` w.r.t. the Haar measure of
        volume ``pi^2``, ``(B,)``, where the family has it in closed form; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form normaliser")

    def exact_mode(self) -> torch.Tensor:
        """The peak of the density ``(B, 3, 3)`` in closed form; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} has no closed-form mode")

    def exact_sample(self, n: int, generator: torch.Generator | None = None) -> torch.Tensor:
        """``n`` exact draws ``(B, n, 3, 3)`` from the continuous density; else ``NotImplementedError``."""
        raise NotImplementedError(f"{type(self).__name__} cannot be sampled off the grid")

    # ------------------------------------------------------------------ derived: continuous density
    @property
    def has_exact_density(self) -> bool:
        """True when the family has a closed-form normaliser (and so a continuous log likelihood)."""
        return type(self).exact_log_normalizer is not PoseDistribution.exact_log_normalizer

    def exact_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        """The continuous log density ``(B, K)`` (Haar measure of volume ``pi^2``), for families with
        a closed-form normaliser."""
        rotations = self._check_query(rotations)
        return self.unnormalized_log_density(rotations) - self.exact_log_normalizer()[:, None]

    # ------------------------------------------------------------------ recalibration
    def tempered(self, temperature: float) -> PoseDistribution:
        """The distribution with density proportional to ``p(R) ** (1 / temperature)`` (module docstring);
        ``self`` at temperature 1. Families whose power stays in the family override this."""
        temperature = check_temperature(temperature)
        return self if temperature == 1.0 else TemperedDistribution(self, temperature)

    # ------------------------------------------------------------------ checks
    def _check_query(self, rotations: torch.Tensor) -> torch.Tensor:
        check_rotation_matrix(rotations, "rotations")
        if rotations.ndim == 4 and rotations.shape[0] != self.batch_size:
            raise ConfigError(
                f"rotations of shape (B, K, 3, 3) must have B = batch size {self.batch_size}, "
                f"got {tuple(rotations.shape)}"
            )
        if rotations.ndim not in (3, 4):
            raise ConfigError(f"rotations must have shape (B, K, 3, 3) or (K, 3, 3), got {tuple(rotations.shape)}")
        return rotations.to(device=self.device, dtype=self.dtype)


float32_methods(PoseDistribution)  # the base class's own methods (subclasses: __init_subclass__)


class TemperedDistribution(PoseDistribution):
    """``base`` raised to the power ``1 / temperature`` and renormalised (on the grid): the unnormalised
    log density divided by the temperature. The mode is ``base``'s; there is no closed-form normaliser
    or exact sampler (the grid protocol's are used)."""

    def __init__(self, base: PoseDistribution, temperature: float):
        if not base.has_density:
            raise DensityNotAvailable(f"{type(base).__name__} has no density to temper")
        self.temperature = check_temperature(temperature)
        if isinstance(base, TemperedDistribution):  # powers compose: (p^(1/a))^(1/b) = p^(1/(ab))
            base, self.temperature = base.base, base.temperature * self.temperature
        self.base = base
        self.batch_size, self.dtype, self.device = base.batch_size, base.dtype, base.device

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        return self.base.unnormalized_log_density(rotations) / self.temperature  # [B, K]

    def exact_mode(self) -> torch.Tensor:
        return self.base.exact_mode()  # a positive power keeps the peak where it is


class PointEstimate(PoseDistribution):
    """The output of a point regressor: one rotation per image and no density.

    :meth:`mode` and :meth:`sample` return the rotation; every density method raises
    :class:`DensityNotAvailable`, and evaluations report the log likelihood and the spread as not
    available.
    """

    has_density = False

    def __init__(self, rotation: torch.Tensor):
        check_rotation_matrix(rotation, "rotation", atol=1e-3)
        if rotation.ndim != 3:
            raise ConfigError(f"rotation must have shape (B, 3, 3), got {tuple(rotation.shape)}")
        self.rotation = rotation
        self.batch_size, self.dtype, self.device = rotation.shape[0], rotation.dtype, rotation.device

    def unnormalized_log_density(self, rotations: torch.Tensor) -> torch.Tensor:
        raise DensityNotAvailable(f"{type(self).__name__} is a point estimate: it has no density")

    def exact_mode(self) -> torch.Tensor:
        return self.rotation

    def mode(self, level: int | None = None, refine: bool = False) -> torch.Tensor:
        return self.rotation

    def sample(self, n: int, level: int | None = None, generator=None, return_index: bool = False):
        if return_index:
            raise DensityNotAvailable("a point estimate has no grid indices")
        return self.rotation[:, None].expand(-1, n, -1, -1)

    def modes(self, level: int = 5, k: int = 5, **_) -> list[tuple[torch.Tensor, torch.Tensor]]:
        return [(r[None], torch.ones(1, dtype=self.dtype, device=self.device)) for r in self.rotation]

    def tempered(self, temperature: float) -> PointEstimate:
        """A point estimate has no density to temper: itself (the temperature is checked)."""
        check_temperature(temperature)
        return self
