"""Helpers for tests of this package and of new layers and methods built on it.

* :mod:`~image2sphere.testing.equivariance`: assertions that a layer is left-equivariant.
* :mod:`~image2sphere.testing.commands`: run a ``python -m ...`` command line inside this process, so
  that a test pays the imports of torch, Lightning, Hydra and e3nn once instead of once per command; start
  one as a process group that leaves nothing behind.
* :mod:`~image2sphere.testing.signal_at`: a callback that sends a signal from inside a chosen moment of a run.
* :mod:`~image2sphere.testing.tiny`: the overrides of a run that takes seconds on a CPU.
"""

from image2sphere.testing.commands import needs_own_process, run_command
from image2sphere.testing.equivariance import assert_left_equivariant, equivariance_error

__all__ = ["assert_left_equivariant", "equivariance_error", "needs_own_process", "run_command"]
